"""What is running and where: the package version, library versions, the machine, and the one progress switch.

Models (:mod:`fusion.base`), stores (:mod:`tactile.dataset`), reports and benchmarks record these from here, so
that a number or a file always says which code and which machine made it.

Progress bars: every long loop of the library draws its bar with :func:`progress_bar`. A bar shows when its
caller asks for one (``progress=True``, the default of the long functions) *and* the process-wide switch is on:
:func:`set_progress` (the command line's ``--no-progress`` and ``--json`` turn it off) or the environment
variable ``VISUOTACTILE_PROGRESS=0``. Written to a file or a pipe instead of a terminal, a bar updates every 30 s.
"""

from __future__ import annotations

import configparser
import contextlib
import hashlib
import os
import platform
import select
import signal
import sys
import threading
import time
from collections.abc import Iterator
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from perception.errors import InvalidArgumentError

#: The distribution name of this toolkit.
DISTRIBUTION = "visuotactile"
#: Environment variable that turns every progress bar off when set to 0 (or "false", "no", "off").
PROGRESS_ENV = "VISUOTACTILE_PROGRESS"

_progress: bool | None = None  # set_progress; None: the environment decides


def checkout_root() -> Path | None:
    """The repository checkout this code runs from (the folder above the packages, holding setup.cfg), or None
    for an installed copy (a wheel installs no setup.cfg, and no ``benchmarks``)."""
    root = Path(__file__).resolve().parents[1]
    return root if (root / "setup.cfg").is_file() else None


@cache
def package_version() -> str:
    """The installed package's version (its metadata), else the ``version`` of the checkout's setup.cfg, else
    "unknown" (a bare copy of the sources)."""
    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        pass
    root = checkout_root()
    if root is None:
        return "unknown"
    cfg = root / "setup.cfg"
    parser = configparser.ConfigParser()
    try:
        parser.read(cfg, encoding="utf-8")
        return parser.get("metadata", "version")
    except (configparser.Error, OSError):
        return "unknown"


def versions(*distributions: str) -> dict[str, str]:
    """Python, numpy and visuotactile versions, plus those of ``distributions`` (pip names, e.g.
    "scikit-learn", "torch", "open3d"; "not installed" when absent). Reads package metadata: imports nothing."""
    found = {"python": platform.python_version(), "numpy": version("numpy"), DISTRIBUTION: package_version()}
    for name in distributions:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = "not installed"
    return found


def sources_digest(roots: dict[str, Path], libraries: tuple[str, ...]) -> str:
    """A 16-hex-digit digest of every ``*.py`` file under each root folder (by its path relative to the root, named by
    the key) and of the installed versions of ``libraries`` (:func:`versions`): any edit, added, moved or removed
    file, or upgrade changes it. What caches of computed results key on, so that results of other code are made
    again."""
    h = hashlib.blake2b(digest_size=8)
    for name in sorted(roots):
        root = Path(roots[name])
        for path in sorted(root.rglob("*.py")):
            h.update(f"{name}/{path.relative_to(root).as_posix()}\0".encode())
            h.update(path.read_bytes())
            h.update(b"\0")
    h.update(repr(sorted(versions(*libraries).items())).encode())
    return h.hexdigest()


#: At most this many cores for this process's own parallel work (None: no limit; :func:`limit_cores`).
_core_limit: int | None = None


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity, and at most :func:`limit_cores`'s), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        cores = len(os.sched_getaffinity(0))
    else:
        cores = os.cpu_count() or 1
    return max(1, min(cores, _core_limit or cores))


def limit_cores(n: int | None) -> None:
    """Let this process's thread pools (ours, BLAS, OpenMP's and Open3D's) use at most ``n`` cores (0 or less: 1);
    None lifts our limit and Open3D's, not a BLAS or OpenMP limit set before.

    A worker process that runs beside others on the same machine calls this so that the workers together use
    each core once instead of each spreading over all of them. Open3D's ray casting otherwise runs on every core
    in every worker: two generation workers on 2 cores took 8 % longer that way (the paper store, medians of three
    alternating runs: 92.7 against 85.5 s, the same bytes).
    """
    import open3d as o3d

    global _core_limit
    limit = None if n is None else max(1, int(n))
    o3d.utility.set_max_threads(limit or 0)  # first: it refuses what it cannot take before anything is changed
    _core_limit = limit
    if limit is not None:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limit)


@contextlib.contextmanager
def cores_limited(n: int) -> Iterator[None]:
    """:func:`limit_cores` for the block only: a process that is lent, not owned (a Ray worker that runs other
    tasks after ours), gets its limits back as they were."""
    import open3d as o3d
    from threadpoolctl import threadpool_limits

    global _core_limit
    before, open3d_before = _core_limit, o3d.utility.get_max_threads()
    with threadpool_limits(None):  # changes nothing on entry; gives BLAS and OpenMP their limits back on exit
        limit_cores(n)
        try:
            yield
        finally:
            _core_limit = before
            o3d.utility.set_max_threads(open3d_before)  # no limit before: now one of every core, the same


def worker_cores(n_workers: int) -> int:
    """Cores each of ``n_workers`` worker processes may use (:func:`limit_cores`), so that together they use each
    usable core once: at least 1."""
    return max(1, usable_cores() // max(1, int(n_workers)))


@contextlib.contextmanager
def without_main_module() -> Iterator[None]:
    """Start ``multiprocessing`` children (spawn, forkserver) that do not re-import the caller's main module.

    Such children run the parent's ``__main__`` again so that objects defined there can be unpickled; a script
    without an ``if __name__ == "__main__":`` guard would then run its work again in every child. Our children
    need nothing from ``__main__`` (their targets and arguments live in importable modules), so the preparation
    data leaves it out while the block starts them.
    """
    from multiprocessing import spawn

    original = spawn.get_preparation_data

    def without_main(name):
        data = original(name)
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    spawn.get_preparation_data = without_main
    try:
        yield
    finally:
        spawn.get_preparation_data = original


@cache
def libc():
    """The C library's functions as ctypes sees them (the process's own symbols), or None where it cannot; loaded
    once per process."""
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


#: The largest process id a system call takes (a C ``pid_t``).
MAX_PID = 2**31 - 1


#: Seconds a worker told to stop (SIGTERM) has to unwind before it is killed: generate's and reproduce's alike.
STOP_GRACE_S = 2.0


def stop_as_told() -> None:
    """Signal set-up of a worker process: ignore SIGINT (its parent decides what an interrupt stops), and leave on
    SIGTERM through SystemExit, which no ``except Exception`` catches, so that every ``finally`` runs on the way (a
    file half written by :func:`perception.atomic.atomic_path` removed, what the process made for the resource
    tracker released) instead of dying where it stands. A native call in progress finishes first."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _unwind)


class Stopped(SystemExit):
    """Raised in a worker by SIGTERM (:func:`stop_as_told`): a SystemExit that code running jobs can tell from a job's
    own ``sys.exit``."""


def _unwind(signum, frame) -> None:
    raise Stopped(128 + signum)


def exit_with(pid: int) -> None:
    """Kill this process (SIGKILL), and the processes it started, as soon as process ``pid`` has exited: a worker's
    guard against outliving the run that started it. Its parent is no guide: a forkserver serves until its last
    child has ended, so a caller terminated or killed would leave its workers computing (and writing) on for
    nobody. Watches a pidfd where the system has one (Linux >= 5.3: no polling, no confusion with a later process
    of the same pid), else polls every half second. Returns at once; the watch runs in a daemon thread.

    Raises:
        InvalidArgumentError: ``pid`` is not an integer in 1 .. :data:`MAX_PID`.
    """
    if isinstance(pid, bool) or not isinstance(pid, int) or not 0 < pid <= MAX_PID:
        raise InvalidArgumentError(f"exit_with: pid must be a positive integer up to {MAX_PID}, got {pid!r}")
    try:
        handle = os.pidfd_open(pid)
    except (AttributeError, OSError):  # no pidfds here, or ``pid`` is gone already (then the poll sees it)
        handle = None

    def watch() -> None:
        if handle is not None:
            watcher = select.poll()  # not select(): it fails on descriptors past 1023
            watcher.register(handle, select.POLLIN)
            while not watcher.poll():  # readable once the process has exited
                pass
        else:
            while _running(pid):
                time.sleep(0.5)
        # first the processes this one started (e.g. a loader's converter): once it is gone they could no longer
        # be traced to it, and would run on for nobody; again while one was started meanwhile, a few times at most
        try:
            for _ in range(3):
                handles = descendant_handles(os.getpid())
                if not handles:
                    break
                kill_handles(handles)
        finally:
            os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name=f"exit-with-{pid}", daemon=True).start()


def descendant_handles(pid: int) -> list[int]:
    """pidfds of the living processes descended from process ``pid`` (its children, theirs, ...), listed from
    /proc/PID/task/*/children (Linux). Each is checked, once opened, to be the child of the process it was listed
    under, so a pid reused meanwhile is never taken for it; a pidfd then follows its process even once it is orphaned.
    [] where the system has no such listing or no pidfds. The caller closes them (:func:`kill_handles`)."""
    handles: list[int] = []
    parents = [pid]
    while parents:
        parent = parents.pop()
        for kid in child_pids(parent):
            try:
                handle = os.pidfd_open(kid)
            except (AttributeError, OSError):
                continue
            if _parent(kid) != parent:
                os.close(handle)
                continue
            handles.append(handle)
            parents.append(kid)
    return handles


def child_pids(pid: int) -> list[int]:
    """The child processes of process ``pid``, from /proc/PID/task/*/children (Linux; [] elsewhere, or once ``pid``
    is gone). A pid may be reused as soon as its process is reaped: hold a pidfd to act on one safely
    (:func:`descendant_handles`)."""
    kids = []
    for listing in Path(f"/proc/{pid}/task").glob("*/children"):
        try:
            kids += [int(kid) for kid in listing.read_text().split()]
        except OSError:  # the thread or the process is gone
            continue
    return kids


def kill_handles(handles: list[int]) -> None:
    """SIGKILL the processes behind the pidfds ``handles`` (:func:`descendant_handles`), those still there, and close
    the pidfds."""
    for handle in handles:
        with contextlib.suppress(OSError):  # ProcessLookupError: gone already
            signal.pidfd_send_signal(handle, signal.SIGKILL)
        os.close(handle)


def _parent(pid: int) -> int | None:
    """The parent process id of ``pid`` (/proc/PID/stat), None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


#: CPU vector extensions worth naming in a report, widest first: oneDNN and Open3D pick their kernels by them, so
#: they explain run-time ratios between machines, and CNN weights that differ in the last bits between machines.
VECTOR_EXTENSIONS = ("amx_tile", "avx512_bf16", "avx512f", "avx2", "asimd")


def cpu_description(cpuinfo: str) -> tuple[str, str]:
    """(CPU model, its widest :data:`VECTOR_EXTENSIONS` joined by "+") read from the text of ``/proc/cpuinfo``;
    empty strings for what it does not say."""
    model, flags = "", set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if key in ("model name", "cpu model") and not model:
            model = " ".join(value.split())
        elif key in ("flags", "features") and not flags:
            flags = set(value.split())
    return model, "+".join(ext for ext in VECTOR_EXTENSIONS if ext in flags)


def _cpu() -> tuple[str, str]:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            return cpu_description(f.read(1 << 20))  # the first CPUs' entries are enough
    except OSError:  # not Linux
        return platform.processor() or "", ""


def machine() -> dict:
    """Where the numbers were measured: platform, processor, CPU model and vector extensions, logical CPUs, usable
    cores, Python."""
    model, vector = _cpu()
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_model": model,
        "cpu_vector": vector,
        "cpu_count": os.cpu_count(),
        "cores_available": usable_cores(),
        "python": platform.python_version(),
    }


def machine_line() -> str:
    """:func:`machine` in one line, for reports."""
    info = machine()
    model, vector = info["cpu_model"], info["cpu_vector"]
    cpu = f"{model} ({vector})" if model and vector else model or vector
    return " ".join(part for part in (info["processor"], cpu) if part) + \
        f" {info['cpu_count']} logical CPUs, {info['cores_available']} usable, Python {info['python']}"


def set_progress(enabled: bool | None) -> None:
    """Turn every progress bar of this process on or off; None: back to the environment's choice."""
    global _progress
    _progress = None if enabled is None else bool(enabled)


def progress_enabled(requested: bool = True) -> bool:
    """Whether a bar that its caller ``requested`` shows: the request, the switch and the environment agree."""
    if not requested:
        return False
    if _progress is not None:
        return _progress
    return os.environ.get(PROGRESS_ENV, "1").strip().lower() not in ("0", "false", "no", "off")


def progress_bar(iterable=None, *, enabled: bool = True, **options):
    """A tqdm bar over ``iterable`` (``options`` go to tqdm: desc, unit, total, ...), shown only when
    :func:`progress_enabled` (``enabled``)."""
    from tqdm import tqdm

    disable = bool(options.pop("disable", False)) or not progress_enabled(enabled)
    stream = options.get("file") or sys.stderr
    try:
        terminal = bool(stream.isatty())
    except (AttributeError, TypeError, ValueError, OSError):  # no stream, a closed one, an odd object
        terminal = False
    if terminal:
        return tqdm(iterable, disable=disable, **options)
    # a log file, not a terminal: a line every half minute, not ten a second (tens of kB per bar otherwise)
    options.setdefault("mininterval", 30.0)
    return _log_bar_class()(iterable, disable=disable, **options)


@cache
def _log_bar_class():
    from tqdm import tqdm

    class LogBar(tqdm):
        """A bar writing to a log: a new postfix waits for the next scheduled line (tqdm would write one at once,
        each epoch of a training run)."""

        def set_postfix(self, ordered_dict=None, refresh=False, **kwargs):
            super().set_postfix(ordered_dict, refresh=refresh, **kwargs)

        def set_postfix_str(self, s="", refresh=False):
            super().set_postfix_str(s, refresh=refresh)

    return LogBar


__all__ = ["DISTRIBUTION", "PROGRESS_ENV", "STOP_GRACE_S", "Stopped", "checkout_root", "child_pids", "cores_limited",
           "descendant_handles", "exit_with", "kill_handles", "limit_cores", "machine", "machine_line",
           "package_version", "progress_bar", "progress_enabled", "set_progress", "sources_digest", "stop_as_told",
           "usable_cores", "versions", "without_main_module", "worker_cores"]
