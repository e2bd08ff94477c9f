"""Run a native call that may abort, segfault or hang in a forked child, with a time limit.

pymeshlab's curvature fits take the whole process down (``double free``, SIGSEGV) or never return on some
meshes, open and closed alike (self-intersections, a vertex shared by two solids, unused vertices, a plain
box, a tetrahedron), and no cheap test tells a safe mesh from an unsafe one. So such calls run in a child
made with a bare ``os.fork()``: copy-on-write, so the mesh is not copied and nothing is re-imported (about
10 ms), and it works from any process, also from a daemonic ``multiprocessing`` worker or a Ray worker,
where ``multiprocessing.Process`` refuses to start children. The result comes back pickled through a pipe;
the parent waits at most ``timeout_s`` and kills the child after that.

A fork copies only the calling thread: a lock that another thread of the parent held at that moment stays held
in the child forever. Open3D's TBB workers are such threads: after any parallel Open3D call in the parent, a
child forked while a worker was still in its task arena waits for it in its next parallel call (seen in
``TriangleMesh.cluster_connected_triangles``: 1 fork in about 200 to 1,200 right after a parallel call). So the
parent watches the child: one asleep without using the CPU for ``stall_s`` seconds is presumed deadlocked (a
computing child runs or waits for the CPU; it is not asleep) and is killed and forked again (:data:`ATTEMPTS` in
all). That presumes what the isolated calls are: native computations that never wait on a clock, a process or
the network, and that give the same result when run again. A function that waits must pass ``stall_s=math.inf``.
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

from perception.errors import InvalidArgumentError

log = logging.getLogger(__name__)

#: Seconds a child may sleep without using the CPU before it is taken as deadlocked (:func:`run_isolated`).
STALL_S = 5.0
#: Children forked per call at most, when the ones before deadlocked.
ATTEMPTS = 3
#: Seconds between looks at the child's state while its result is awaited.
POLL_S = 0.25


#: What went wrong in an isolated call (:attr:`IsolatedCallFailed.kind`).
FAILURES = ("crashed", "timed out", "deadlocked")


class IsolatedCallFailed(RuntimeError):
    """The isolated call crashed (killed by a signal / exited without a result), ran out of time or deadlocked.

    Attributes:
        kind: one of :data:`FAILURES`.
        reason: ``kind``, then any details in brackets (for messages).
    """

    def __init__(self, what: str, kind: str, details: str | None = None) -> None:
        if kind not in FAILURES:
            raise ValueError(f"IsolatedCallFailed: kind must be one of {FAILURES}, got {kind!r}")
        self.what, self.kind, self.details = what, kind, details
        self.reason = kind if details is None else f"{kind} ({details})"
        super().__init__(f"{what}: {self.reason}")

    def __reduce__(self):  # sent back from a worker process whole, not as its message alone
        return type(self), (self.what, self.kind, self.details)


def _quiet_child() -> None:
    """In the child: an expected abort should print no stack (faulthandler) and no glibc message, and
    native chatter on stdout/stderr should not reach the caller's terminal."""
    import faulthandler

    faulthandler.disable()
    os.environ["LIBC_FATAL_STDERR_"] = "1"  # glibc's fatal messages go to stderr (silenced below), not the tty
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    os.close(devnull)
    # The parent's handlers (pytest, a user's Ctrl-C handler) must not run here; the parent kills us.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def run_isolated(func: Callable[..., Any], *args: Any, timeout_s: float, what: str = "isolated call",
                 stall_s: float | None = None) -> Any:
    """``func(*args)`` evaluated in a forked child; its return value, or the exception it raised, re-raised here.

    Args:
        func: a function whose arguments and result pickle (numpy arrays do), that computes and may be run
            again (module docstring).
        timeout_s: wall-clock limit per child, seconds; the child is killed (SIGKILL) after it.
        what: names the call in messages.
        stall_s: seconds a child may sleep without using the CPU before it is killed and forked again (see the
            module docstring), at most :data:`ATTEMPTS` children in all; None: :data:`STALL_S`; ``math.inf``: no
            watch. Worst case: ``(ATTEMPTS - 1) * (stall_s + POLL_S) + timeout_s``.

    Raises:
        InvalidArgumentError: ``stall_s`` not a number above 0 (before anything is forked).
        IsolatedCallFailed: the child died without a result (abort, segfault, ``os._exit``), timed out, or every
            child was presumed deadlocked.
        Exception: whatever ``func`` raised in the child (if it pickles; else IsolatedCallFailed).
    """
    stall_s = STALL_S if stall_s is None else stall_s
    if isinstance(stall_s, bool) or not isinstance(stall_s, (int, float)) or not stall_s > 0:
        raise InvalidArgumentError(f"{what}: stall_s must be a number of seconds above 0 (math.inf: no watch), "
                                   f"got {stall_s!r}")
    for attempt in range(1, ATTEMPTS + 1):
        try:
            return _run_child(func, args, timeout_s, what, stall_s)
        except _Deadlocked:
            log.warning("%s: child %d of %d slept %g s without using the CPU (presumed deadlocked: a lock held at "
                        "the fork); %s", what, attempt, ATTEMPTS, stall_s,
                        "forking again" if attempt < ATTEMPTS else "giving up")
    children = "1 child" if ATTEMPTS == 1 else f"{ATTEMPTS} children in a row"
    raise IsolatedCallFailed(what, "deadlocked", f"{children} slept {stall_s:g} s without using the CPU")


class _Deadlocked(Exception):
    """The child slept without using the CPU for ``stall_s`` seconds (it has been killed)."""


def _run_child(func: Callable[..., Any], args: tuple, timeout_s: float, what: str, stall_s: float) -> Any:
    """One forked child of :func:`run_isolated`."""
    sys.stdout.flush()
    sys.stderr.flush()
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # ------------------------------------------------------------------ child
        code = 0
        try:
            os.close(read_fd)
            _quiet_child()
            try:
                payload = (True, func(*args))
            except BaseException as exc:  # noqa: BLE001 - everything goes back to the parent
                payload = (False, exc)
            try:
                data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
            except Exception:  # noqa: BLE001 - an unpicklable exception: send its text
                data = pickle.dumps((False, RuntimeError(repr(payload[1]))))
            view = memoryview(data)
            while view:
                view = view[os.write(write_fd, view) :]
            os.close(write_fd)  # EOF now: the parent goes on while this process is torn down
        except BaseException:  # noqa: BLE001
            code = 1
        finally:
            os._exit(code)  # never run the parent's atexit handlers or return into its stack
    # ------------------------------------------------------------------------------- parent
    os.close(write_fd)
    _reap_finished()
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    watch = _Watch(pid, stall_s)
    done = False
    try:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise IsolatedCallFailed(what, "timed out")
            ready, _, _ = select.select([read_fd], [], [], min(remaining, POLL_S))
            if not ready:
                if watch.stalled():
                    raise _Deadlocked
                continue
            chunk = os.read(read_fd, 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
        done = True
    finally:
        os.close(read_fd)
        if not done:
            _kill(pid)
    data = b"".join(chunks)
    try:
        ok, value = pickle.loads(data) if data else (None, None)
    except Exception:  # noqa: BLE001 - truncated: the child died while writing
        ok = None
    if ok is None:
        try:
            _, status = os.waitpid(pid, 0)
            how = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit {os.WEXITSTATUS(status)}"
        except ChildProcessError:  # SIGCHLD ignored by the application: the child was reaped for us
            how = "exit status unknown"
        raise IsolatedCallFailed(what, "crashed", how)
    # The child is exiting (its teardown takes tens of ms for a large process): reap it later, not now.
    _UNREAPED.append(pid)
    _reap_finished()
    if ok:
        return value
    raise value


class _Watch:
    """Whether a child has slept (state S) without using the CPU for ``stall_s`` seconds on end (Linux's
    ``/proc/<pid>/stat``; where that cannot be read, never)."""

    def __init__(self, pid: int, stall_s: float) -> None:
        self.pid, self.stall_s = pid, stall_s
        self.last = self._sample()
        self.since = time.monotonic()

    def _sample(self) -> tuple[str, int] | None:
        """(state, CPU clock ticks of all its threads), or None."""
        try:
            with open(f"/proc/{self.pid}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()  # the name may hold spaces and brackets
            return fields[0].decode(), int(fields[11]) + int(fields[12])
        except (OSError, IndexError, ValueError):
            return None

    def stalled(self) -> bool:
        now = self._sample()
        if now is None:
            return False
        if now[0] != "S" or self.last is None or now[1] != self.last[1]:
            self.last, self.since = now, time.monotonic()
            return False
        return time.monotonic() - self.since >= self.stall_s


#: Children that delivered their result but may still be exiting; reaped without blocking on later calls.
_UNREAPED: list[int] = []


def _reap_finished() -> None:
    """Reap the children of earlier calls that have exited (no zombies pile up)."""
    for pid in list(_UNREAPED):
        try:
            finished, _ = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:  # already reaped (another thread, or SIGCHLD ignored)
            finished = pid
        if finished:
            try:
                _UNREAPED.remove(pid)
            except ValueError:  # another thread removed it first
                pass


def _kill(pid: int) -> None:
    """Kill and reap the child ``pid`` (it may already be gone)."""
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    try:
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass


__all__ = ["ATTEMPTS", "FAILURES", "STALL_S", "IsolatedCallFailed", "run_isolated"]
