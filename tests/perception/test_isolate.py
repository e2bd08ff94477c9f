"""The forked child that keeps native crashes and hangs out of the caller's process (perception.isolate)."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
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
    assert info.value.reason.startswith("crashed")
    assert run_isolated(int, "7", timeout_s=30) == 7  # this process still works


def test_a_hang_is_cut_at_the_time_limit():
    start = time.perf_counter()
    with pytest.raises(IsolatedCallFailed, match="timed out"):
        run_isolated(_sleep, 60.0, timeout_s=0.5)
    assert time.perf_counter() - start < 5.0


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
