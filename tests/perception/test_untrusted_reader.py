"""perception.untrusted at its edges: a FIFO or device is refused as "not a regular file" (never read, never waited
on), a file of exactly ``max_bytes`` is read, and refusing a folder leaks no file descriptor."""

from __future__ import annotations

import os

import pytest

from perception.untrusted import open_regular, read_json


def test_a_fifo_is_refused_as_not_a_regular_file(tmp_path):
    fifo = tmp_path / "meta.json"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match=r"not a regular file \(a FIFO\)"):
        read_json(fifo, 100)


def test_a_device_is_refused_as_not_a_regular_file():
    with pytest.raises(ValueError, match=r"not a regular file \(a character device\)"):
        read_json("/dev/zero", 100)


def test_a_file_of_exactly_max_bytes_is_read(tmp_path):
    path = tmp_path / "meta.json"
    path.write_text('{"a": [1, 2]}')  # 13 bytes
    assert read_json(path, 13) == {"a": [1, 2]}
    with pytest.raises(ValueError, match="13 bytes, more than the 12"):
        read_json(path, 12)


def test_refusing_a_folder_says_so_and_leaks_no_file_descriptor(tmp_path):
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(5):
        with pytest.raises(ValueError, match=r"not a regular file \(a folder\)"):
            open_regular(tmp_path, 100)
    assert len(os.listdir("/proc/self/fd")) == before


def test_a_file_grown_after_its_size_check_is_read_no_further(tmp_path, monkeypatch):
    """The size is checked from fstat, then at most max_bytes + 1 are read: a file that grew in between (simulated:
    fstat reports 10 bytes) is refused, not parsed from a cut-off prefix."""
    path = tmp_path / "meta.json"
    path.write_text('{"a": 1}' + " " * 200)
    real = os.fstat
    monkeypatch.setattr(os, "fstat", lambda fd: os.stat_result((*real(fd)[:6], 10, *real(fd)[7:10])))
    with pytest.raises(ValueError, match="more than the 100 bytes this file may hold"):
        read_json(path, 100)
