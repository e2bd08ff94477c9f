"""What every benchmark shares: the machine description and median timing."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path

import numpy as np

#: The shared real data (``$VISUOTACTILE_DATA``, default ``../shared/data`` beside the repository).
DATA = Path(os.environ.get("VISUOTACTILE_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def machine() -> dict:
    """Where the numbers were measured: platform, cores, library versions."""
    import open3d

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cores_available": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "open3d": open3d.__version__,
        "pymeshlab": version("pymeshlab"),
    }


def median_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Median wall time (s) of ``repeats`` calls of ``fn``, and the last call's result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result
