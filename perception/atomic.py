"""Atomic file writes: a file is either its old self or complete, never half-written.

Everything the toolkit writes (figures, summaries, later dataset chunks) goes through here, so a run
interrupted mid-write leaves no truncated file behind: the data goes to a temporary file in the same
folder, then ``os.replace`` swaps it in (atomic on POSIX for a single file system).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path``, on error it is removed.

    The parent folder is created if needed. The temporary name keeps the suffix, so writers that infer the
    format from it (matplotlib, numpy) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The name is ours before the file exists: an interrupt (KeyboardInterrupt, a stopped worker's SystemExit) raised
    # as the file is created, before any statement after it runs, still removes it.
    tmp = None
    try:
        while tmp is None:
            tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}{path.suffix}")
            try:
                # Mode 0o666 less the umask, as open() gives (mkstemp's 0o600 made reports unreadable to others);
                # a file being replaced keeps its own mode.
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            except FileExistsError:  # another writer's file: not ours to remove
                tmp = None
        with contextlib.suppress(FileNotFoundError):
            os.chmod(tmp, stat.S_IMODE(os.stat(path).st_mode))
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.remove(tmp)


#: The name :func:`atomic_path` gives a temporary file: ``.<name>.<8 hex digits><the name's suffix>``.
_TEMPORARY = re.compile(r"\.(?P<name>.+)\.[0-9a-f]{8}(?P<suffix>(\.[^./]*)?)")


def stale_temporaries(folder: str | Path) -> list[Path]:
    """The files under ``folder`` named as :func:`atomic_path` names its temporary files: what a writer killed before
    it could clean up (SIGKILL, a power cut) leaves. Only call this while no writer can be running there (under the
    folder's lock): a live writer's temporary file looks the same."""
    stale = []
    for path in Path(folder).rglob(".*"):
        match = _TEMPORARY.fullmatch(path.name)
        if match and path.is_file() and not path.is_symlink() \
                and Path(match["name"]).suffix == match["suffix"]:
            stale.append(path)
    return sorted(stale)


def _nearest_existing(path: Path) -> Path:
    """``path`` if it exists, else its nearest existing parent (the folder a new file or folder goes in)."""
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path.cwd()


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(_nearest_existing(folder), "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def _check_writable(path: Path, what: str, place: Path) -> None:
    """Refuse ``path`` when the nearest existing folder of ``place`` takes no new file: a file is really created and
    removed there (``os.access`` says yes to root in ``/proc`` and ``/sys``, and on read-only mounts; writing is
    the only sure test)."""
    import tempfile

    from perception.errors import InvalidArgumentError

    place = _nearest_existing(place)
    try:
        fd, probe = tempfile.mkstemp(prefix=".visuotactile-write-test-", dir=place)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise InvalidArgumentError(f"{what} {str(path)!r}: cannot write in {str(place)!r} ({reason}); "
                                   "give a place you can write to") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.remove(probe)


def _check_parents(path: Path, what: str) -> None:
    from perception.errors import InvalidArgumentError

    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InvalidArgumentError(f"{what} {str(path)!r}: {str(parent)!r} is a file, not a folder")
            break


def check_output_file(path, what: str = "output file") -> Path:
    """Check, before any work, that a file can be written atomically at ``path``: a non-empty name, not a folder, no
    file where a parent folder must be, a name short enough for the temporary name :func:`atomic_path` adds, and
    a folder that takes a new file (a real write test).

    Raises:
        InvalidArgumentError: naming ``what``, the path and the problem.
    """
    from perception.errors import InvalidArgumentError

    if path is None or not str(path).strip():
        raise InvalidArgumentError(f"{what}: an empty path; give a file name")
    path = Path(path)
    if path.is_dir() or not path.name or path.name in (".", ".."):
        raise InvalidArgumentError(f"{what} {str(path)!r}: is a folder; give a file name inside it")
    _check_parents(path, what)
    longest = len(os.fsencode(f".{path.name}.{'0' * 8}{path.suffix}"))
    if longest > _name_max(path.parent):
        raise InvalidArgumentError(f"{what} {str(path)!r}: the name is too long ({len(os.fsencode(path.name))} bytes; "
                                   f"at most {_name_max(path.parent) - 11 - len(os.fsencode(path.suffix))} here)")
    _check_writable(path, what, path.parent)
    return path


def check_output_folder(path, what: str = "output folder") -> Path:
    """Check, before any work, that ``path`` is or can become a folder (not a file, no file among its parents) in a
    place that takes a new file (a real write test).

    Raises:
        InvalidArgumentError: naming ``what``, the path and the problem.
    """
    from perception.errors import InvalidArgumentError

    if path is None or not str(path).strip():
        raise InvalidArgumentError(f"{what}: an empty path; give a folder")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InvalidArgumentError(f"{what} {str(path)!r}: is a file, not a folder")
    _check_parents(path, what)
    if len(os.fsencode(path.name)) > _name_max(path.parent):
        raise InvalidArgumentError(f"{what} {str(path)!r}: the name is too long")
    _check_writable(path, what, path)
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def save_figure(fig, path: str | Path, **savefig_kwargs) -> Path:
    """``fig.savefig`` to ``path`` atomically (format from the suffix); returns the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **savefig_kwargs)
    return Path(path)
