"""What every benchmark shares: the machine description and median timing."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

from perception.data import DATA  # noqa: F401  (the benchmarks import it from here)


def machine() -> dict:
    """Where the numbers were measured: platform, cores, library versions (:mod:`perception.runtime`)."""
    from perception.runtime import machine as this_machine
    from perception.runtime import versions

    return {**this_machine(), **versions("open3d", "pymeshlab")}


def median_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Median wall time (s) of ``repeats`` calls of ``fn``, and the last call's result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result
