"""Reading files users exchange (stores, recordings, caches): only regular files, opened without blocking, their
size checked before a byte is read, JSON nesting bounded.

A FIFO or a device named like a data file would block a reader forever or never end; a sparse file of a few bytes
on disk can claim gigabytes; JSON nested a hundred thousand deep overflows the parser's recursion.

Examples:
    >>> import tempfile, pathlib
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "meta.json"
    >>> _ = path.write_text('{"a": [1, 2]}')
    >>> read_json(path, 100)
    {'a': [1, 2]}
    >>> read_json(path, 5)
    Traceback (most recent call last):
    ...
    ValueError: 13 bytes, more than the 5 this file may hold
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import BinaryIO


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, in words ("FIFO", "character device", ...)."""
    for test, kind in ((stat.S_ISFIFO, "FIFO"), (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
                       (stat.S_ISSOCK, "socket"), (stat.S_ISDIR, "folder"), (stat.S_ISLNK, "symlink")):
        if test(mode):
            return kind
    return "special file"


def open_regular(path: str | Path, max_bytes: int) -> BinaryIO:
    """``path`` opened for binary reading, never blocking, after checking (``fstat`` on the open file) that it is a
    regular file of at most ``max_bytes``.

    Raises:
        OSError: it cannot be opened. ValueError: not a regular file, or larger (the problem only: callers name the
        file).
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    try:  # checked on the raw descriptor: fdopen itself refuses a folder, and the descriptor must not leak
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"not a regular file (a {file_kind(info.st_mode)})")
        if info.st_size > max_bytes:
            raise ValueError(f"{info.st_size} bytes, more than the {max_bytes} this file may hold")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_json(path: str | Path, max_bytes: int):
    """The parsed JSON file ``path`` (:func:`open_regular`; at most ``max_bytes`` read even if it grows meanwhile).

    Raises:
        OSError: it cannot be opened or read. ValueError: not a regular file, larger than ``max_bytes``, not UTF-8
        JSON, or nested too deeply for the parser.
    """
    with open_regular(path, max_bytes) as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise ValueError(f"more than the {max_bytes} bytes this file may hold")
    try:
        return json.loads(data.decode("utf-8"))
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None


__all__ = ["file_kind", "open_regular", "read_json"]
