"""The stall watch of perception.isolate.run_isolated (break attempt 2026-12-07): what it must not take for a
deadlock (a child computing longer than the stall limit, a stopped child, a child whose threads compute while its
main thread waits, a child that sleeps briefly and then computes), and the surface call's hint per reason."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from perception import isolate
from perception.isolate import IsolatedCallFailed, run_isolated

pytestmark = pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="the stall watch reads /proc")


@pytest.fixture
def forks(monkeypatch):
    """The pids of the children run_isolated forks, in order."""
    pids: list[int] = []
    real_fork = os.fork

    def counting_fork():
        pid = real_fork()
        if pid:
            pids.append(pid)
        return pid

    monkeypatch.setattr(isolate.os, "fork", counting_fork)
    return pids


def _stop_myself() -> str:
    os.kill(os.getpid(), signal.SIGSTOP)  # state T (stopped), not S: someone stopped it, it did not deadlock
    return "resumed"


def test_a_stopped_child_is_not_taken_for_deadlocked(forks):
    def resume_later():
        deadline = time.monotonic() + 10
        while not forks and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(1.5)  # three stall limits
        for pid in forks:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass

    resumer = threading.Thread(target=resume_later, daemon=True)
    resumer.start()
    assert run_isolated(_stop_myself, timeout_s=30, stall_s=0.5) == "resumed"
    resumer.join()
    assert len(forks) == 1


def _spin(seconds: float) -> str:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass
    return "spun"


def test_a_child_that_computes_longer_than_the_stall_limit_is_left_alone(forks):
    assert run_isolated(_spin, 2.0, timeout_s=60, stall_s=0.5) == "spun"
    assert len(forks) == 1


def _threads_compute_while_main_waits(seconds: float) -> str:
    workers = [threading.Thread(target=_spin, args=(seconds,)) for _ in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()  # the main thread sleeps (state S) while its workers use the CPU (user time)
    return "joined"


def test_a_child_whose_threads_compute_while_its_main_thread_waits_is_left_alone(forks):
    assert run_isolated(_threads_compute_while_main_waits, 3.0, timeout_s=60, stall_s=1.0) == "joined"
    assert len(forks) == 1


def _sleep_then_compute(sleep_s: float, spin_s: float) -> str:
    time.sleep(sleep_s)
    _spin(spin_s)
    return "done"


def test_a_child_that_sleeps_less_than_the_stall_limit_then_computes_is_left_alone(forks):
    assert run_isolated(_sleep_then_compute, 0.6, 1.0, timeout_s=60, stall_s=1.5) == "done"
    assert len(forks) == 1


def _raise_reason(kind, details):
    def fake(*args, what, **kwargs):
        raise IsolatedCallFailed(what, kind, details)
    return fake


@pytest.mark.parametrize("kind, details, reason, hint, not_hint", [
    ("deadlocked", "3 children in a row slept 5 s without using the CPU",
     "deadlocked (3 children in a row slept 5 s without using the CPU)", "lock", "check the cloud"),
    ("timed out", None, "timed out", "check the cloud", "lock"),
    ("crashed", "signal 11", "crashed (signal 11)", "check the cloud", "lock"),
])
def test_the_surface_call_hints_per_reason(monkeypatch, kind, details, reason, hint, not_hint):
    from perception.errors import InvalidMeshError
    from perception.reconstruct import surface

    monkeypatch.setattr(surface, "run_isolated", _raise_reason(kind, details))
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3)) * 20.0
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    with pytest.raises(InvalidMeshError) as info:
        surface._surface_isolated(points, normals, "poisson", 6, 0.0, 1000, None, "cloud")
    assert reason in str(info.value) and hint in str(info.value) and not_hint not in str(info.value)


def _ok() -> str:
    return "ok"


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), "5", True])
def test_a_stall_limit_that_is_not_a_positive_number_is_refused_before_forking(forks, bad):
    from perception.errors import InvalidArgumentError

    with pytest.raises(InvalidArgumentError, match="stall_s must be a number of seconds above 0"):
        run_isolated(_ok, timeout_s=30, stall_s=bad, what="bad stall")
    assert forks == []


def test_an_infinite_stall_limit_turns_the_watch_off(forks):
    assert run_isolated(_sleep_then_compute, 1.0, 0.1, timeout_s=30, stall_s=float("inf")) == "done"
    assert len(forks) == 1


def test_every_presumed_deadlock_is_logged_the_last_one_too(monkeypatch, caplog):
    """benchmarks.fork_stress counts these lines: one per deadlocked child, retried or not."""
    lock = threading.Lock()
    lock.acquire()
    try:
        with pytest.raises(IsolatedCallFailed, match="deadlocked"):
            run_isolated(_wait_for, lock, timeout_s=30, stall_s=0.5, what="lock")
    finally:
        lock.release()
    lines = [r.getMessage() for r in caplog.records if "without using the CPU" in r.getMessage()]
    assert len(lines) == isolate.ATTEMPTS
    assert lines[-1].endswith("giving up") and all(line.endswith("forking again") for line in lines[:-1])


def _wait_for(lock) -> None:
    with lock:
        pass
