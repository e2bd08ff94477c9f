"""One module per ``visuotactile`` subcommand; each defines ``register(subparsers)`` (see :mod:`fusion.cli`).

Also the output-place checks every subcommand uses before any work (:func:`check_output_file`,
:func:`check_output_folder`): those of :mod:`perception.atomic` (names, parents) plus a real write test.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path


def print_json(result) -> None:
    """A ``--json`` result: one JSON document on stdout (logs and progress go to stderr)."""
    json.dump(result, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def _nearest_existing(path: Path) -> Path:
    """``path`` if it exists, else its nearest existing parent (the folder a new file or folder goes in)."""
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path.cwd()


def check_writable_place(path, what: str, *, folder: bool) -> None:
    """Refuse, before any work, an output ``path`` whose nearest existing folder takes no new file: a file is
    really created and removed there (``os.access`` says yes to root in ``/proc`` and ``/sys``, and on read-only
    mounts; writing is the only sure test).

    Raises:
        InvalidArgumentError: naming ``what``, the path, the folder and the reason.
    """
    import tempfile

    from perception.errors import InvalidArgumentError

    path = Path(path)
    place = _nearest_existing(path if folder else path.parent)
    try:
        fd, probe = tempfile.mkstemp(prefix=".visuotactile-write-test-", dir=place)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise InvalidArgumentError(f"{what} {str(path)!r}: cannot write in {str(place)!r} ({reason}); "
                                   "give a place you can write to") from None
    os.close(fd)
    try:
        os.remove(probe)
    except OSError:
        pass


def check_output_file(path, what: str = "output file") -> Path:
    """:func:`perception.atomic.check_output_file` and a write test of its folder (:func:`check_writable_place`).

    Raises:
        InvalidArgumentError: naming ``what``, the path and the problem.
    """
    from perception.atomic import check_output_file as check_names

    path = check_names(path, what)
    check_writable_place(path, what, folder=False)
    return path


def check_output_folder(path, what: str = "output folder") -> Path:
    """:func:`perception.atomic.check_output_folder` and a write test of the folder or its nearest existing parent.

    Raises:
        InvalidArgumentError: naming ``what``, the path and the problem.
    """
    from perception.atomic import check_output_folder as check_names

    path = check_names(path, what)
    check_writable_place(path, what, folder=True)
    return path
