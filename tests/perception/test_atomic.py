"""Atomic writes: complete or untouched, never half-written, no temporary files left behind."""

from __future__ import annotations

import pytest

from perception.atomic import atomic_path, write_text


def test_write_replaces_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "sub" / "summary.json"
    write_text(target, "first")
    write_text(target, "second")
    assert target.read_text() == "second"
    assert sorted(p.name for p in target.parent.iterdir()) == ["summary.json"]


def test_interrupted_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "figure.png"
    target.write_text("old")
    with pytest.raises(KeyboardInterrupt), atomic_path(target) as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["figure.png"]


def test_an_interrupt_as_the_temporary_file_is_created_removes_it(tmp_path, monkeypatch):
    """A signal handled just after the temporary file is created (a stopped generation worker's SystemExit, Ctrl-C),
    before any statement after the creation runs: the file is still removed (it was left in a store once, in CI)."""
    from perception import atomic

    real_open = atomic.os.open

    def open_then_interrupted(*args, **kwargs):
        real_open(*args, **kwargs)  # the file exists now
        raise SystemExit(143)

    monkeypatch.setattr(atomic.os, "open", open_then_interrupted)
    target = tmp_path / "chunk"
    with pytest.raises(SystemExit), atomic_path(target):
        pass
    assert list(tmp_path.iterdir()) == []
