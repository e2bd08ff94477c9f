"""The forked child that keeps native crashes and hangs out of the caller's process (perception.isolate)."""

from __future__ import annotations

import ctypes
import json
import multiprocessing
import os
import threading
import time

import numpy as np
import pytest

from perception import isolate
from perception.isolate import IsolatedCallFailed, run_isolated


def _abort() -> None:
    os.abort()  # what pymeshlab's "double free or corruption" ends in: SIGABRT


def _segfault() -> None:
    ctypes.string_at(0)  # read address 0: SIGSEGV


def _sleep(seconds: float) -> str:
    time.sleep(seconds)
    return "woke"


def _raise() -> None:
    raise KeyError("from the child")


def test_returns_the_childs_value():
    values = np.arange(200_000, dtype=np.float64)  # 1.6 MB: more than one pipe buffer
    out = run_isolated(np.cumsum, values, timeout_s=30)
    np.testing.assert_array_equal(out, np.cumsum(values))


@pytest.mark.parametrize("crash", [_abort, _segfault], ids=["abort", "segfault"])
def test_a_native_crash_is_reported_and_the_caller_survives(crash):
    with pytest.raises(IsolatedCallFailed, match="crashed") as info:
        run_isolated(crash, timeout_s=30, what="crash test")
    assert info.value.kind == "crashed" and info.value.reason.startswith("crashed (")
    assert run_isolated(int, "7", timeout_s=30) == 7  # this process still works


def test_a_hang_is_cut_at_the_time_limit():
    start = time.perf_counter()
    with pytest.raises(IsolatedCallFailed, match="timed out") as info:
        run_isolated(_sleep, 60.0, timeout_s=0.5)
    assert time.perf_counter() - start < 5.0
    assert info.value.kind == info.value.reason == "timed out"


def test_the_childs_exception_is_raised_here():
    with pytest.raises(KeyError, match="from the child"):
        run_isolated(_raise, timeout_s=30)


def _from_a_daemonic_worker(_: int) -> str:
    """In a multiprocessing.Pool worker (daemonic: multiprocessing refuses to start children there)."""
    try:
        run_isolated(_abort, timeout_s=30)
    except IsolatedCallFailed as exc:
        return exc.reason
    return "no failure"


def test_works_inside_a_daemonic_pool_worker():
    with multiprocessing.get_context("fork").Pool(1) as pool:
        reasons = pool.map(_from_a_daemonic_worker, [0])
    assert reasons[0].startswith("crashed")


def test_finished_children_are_reaped():
    for _ in range(5):
        run_isolated(int, "1", timeout_s=30)
    time.sleep(1.0)
    run_isolated(int, "1", timeout_s=30)  # reaps the children of the calls before, which have exited
    assert len(isolate._UNREAPED) <= 1  # at most the last one, maybe still exiting


# A fork copies only the calling thread: a lock another thread holds at that moment stays held in the child.
_HELD = threading.Lock()


def _take_the_lock() -> str:
    with _HELD:  # in a child forked while a parent thread held it: blocks for ever, asleep
        return "took it"


def _hold_the_lock_while_forking(release_after_forks: int | None):
    """A parent thread holds _HELD; it lets go once ``release_after_forks`` children were forked (None: never)."""
    forks = [0]
    real_fork = os.fork

    def counting_fork():
        pid = real_fork()
        if pid:
            forks[0] += 1
            if release_after_forks is not None and forks[0] >= release_after_forks and _HELD.locked():
                _HELD.release()
        return pid

    _HELD.acquire()
    return forks, counting_fork


@pytest.fixture
def fork_with_a_held_lock(monkeypatch):
    def start(release_after_forks):
        forks, fork = _hold_the_lock_while_forking(release_after_forks)
        monkeypatch.setattr(isolate.os, "fork", fork)
        return forks

    yield start
    if _HELD.locked():
        _HELD.release()


def test_a_child_deadlocked_at_fork_is_forked_again(fork_with_a_held_lock, caplog):
    forks = fork_with_a_held_lock(release_after_forks=1)  # the first child inherits the held lock, the second not
    start = time.perf_counter()
    assert run_isolated(_take_the_lock, timeout_s=60, stall_s=1.0, what="lock test") == "took it"
    took = time.perf_counter() - start
    assert forks[0] == 2
    assert 1.0 <= took < 10.0  # the stall limit, not the 60 s time limit
    assert "lock test: child 1 of 3 slept 1 s without using the CPU" in caplog.text


def test_children_that_always_deadlock_are_reported_long_before_the_time_limit(fork_with_a_held_lock):
    forks = fork_with_a_held_lock(release_after_forks=None)
    start = time.perf_counter()
    with pytest.raises(IsolatedCallFailed, match="deadlocked") as info:
        run_isolated(_take_the_lock, timeout_s=60, stall_s=0.5, what="lock test")
    assert forks[0] == isolate.ATTEMPTS == 3
    assert info.value.kind == "deadlocked" and info.value.reason.startswith("deadlocked (3 children")
    assert time.perf_counter() - start < 20.0


def test_the_fork_stress_benchmark_counts_its_calls(capsys):
    from benchmarks import fork_stress

    assert fork_stress.main(["--calls", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["calls"], out["attempts"], out["failed_calls"]) == (2, isolate.ATTEMPTS, 0)
    assert 0 < out["median_s"] <= out["max_s"]


def test_a_failure_of_an_unknown_kind_is_a_bug_of_ours():
    with pytest.raises(ValueError, match="kind must be one of"):
        IsolatedCallFailed("x", "exploded")


def test_a_failure_survives_pickling_whole():
    import pickle

    back = pickle.loads(pickle.dumps(IsolatedCallFailed("mesh m: pymeshlab curvature", "crashed", "signal 6")))
    assert (back.kind, back.reason, str(back)) == ("crashed", "crashed (signal 6)",
                                                   "mesh m: pymeshlab curvature: crashed (signal 6)")
