"""Resource limits: every count and size that comes from a user, a store, a model file or a recording is checked
against these *before* anything is allocated or looped over, so a 1 kB file or a typo on the command line cannot
make the toolkit allocate gigabytes or loop for days.

Each limit has a default (far above the paper's sizes: 950 contours per object, 25 probes, 32 x 32 taxels,
22,800 sequences) and an environment variable that sets it, e.g. ``VISUOTACTILE_MAX_CONTOURS=500000``. A refused
value raises an error naming the value, the limit and the variable (:func:`check_count`, :func:`check_bytes`).

Examples:
    >>> check_count("touches", 8, "--touches")
    8
    >>> check_count("touches", 10**8, "--touches")
    Traceback (most recent call last):
    ...
    perception.errors.InvalidArgumentError: --touches: 100000000 is above the limit of 10000 touches per decision (set VISUOTACTILE_MAX_TOUCHES to raise it)
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from perception.errors import InvalidArgumentError


@dataclass(frozen=True)
class Limit:
    """One limit: its environment variable, default and what it counts (for messages)."""

    env: str
    default: int
    counts: str


def _half_of_memory_mb() -> int:
    try:
        return max(256, os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2**21)
    except (ValueError, OSError, AttributeError):
        return 8192


#: name -> Limit. ``memory_mb`` bounds one allocation the toolkit makes from a count it was given (default: half
#: of the machine's memory).
LIMITS: dict[str, Limit] = {
    "objects": Limit("VISUOTACTILE_MAX_OBJECTS", 100_000, "objects"),
    "contours": Limit("VISUOTACTILE_MAX_CONTOURS", 100_000, "contours per object and strategy"),
    "sequences": Limit("VISUOTACTILE_MAX_SEQUENCES", 10_000_000, "sequences"),
    "probes": Limit("VISUOTACTILE_MAX_PROBES", 10_000, "probes per contour"),
    "taxels": Limit("VISUOTACTILE_MAX_TAXELS", 1 << 20, "taxels per frame"),
    "touches": Limit("VISUOTACTILE_MAX_TOUCHES", 10_000, "touches per decision"),
    "views": Limit("VISUOTACTILE_MAX_VIEWS", 1_000, "camera views"),
    "frames": Limit("VISUOTACTILE_MAX_FRAMES", 10_000, "frames in a recording"),
    "image_pixels": Limit("VISUOTACTILE_MAX_IMAGE_PIXELS", 40_000_000, "pixels per image"),
    # A parsed mesh or point file takes about 3.5 times its size in memory; a 16k-triangle scan is 1-2 MB.
    "file_mb": Limit("VISUOTACTILE_MAX_FILE_MB", 512, "MB per mesh or point file"),
    "memory_mb": Limit("VISUOTACTILE_MAX_MEMORY_MB", 0, "MB in one allocation"),  # 0: half of the memory
}


def limit(name: str) -> int:
    """The current value of limit ``name`` (its environment variable, else the default).

    Raises:
        InvalidArgumentError: an unknown name, or the variable is set to something other than a positive integer.
    """
    if name not in LIMITS:
        raise InvalidArgumentError(f"unknown limit {name!r}; the limits are {', '.join(LIMITS)}")
    spec = LIMITS[name]
    text = os.environ.get(spec.env)
    if text is None or not text.strip():
        return spec.default or _half_of_memory_mb()
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise InvalidArgumentError(f"{spec.env}={text!r}: expected a positive integer ({spec.counts})")
    return value


def check_count(name: str, value, what: str, error: type[Exception] = InvalidArgumentError) -> int:
    """``value`` as an int when it is an integer within limit ``name``; else raise ``error`` naming ``what``, the
    value, the limit and its environment variable. Negative values are refused too (counts are never negative).
    """
    if isinstance(value, bool):
        raise error(f"{what}: expected an integer, got {value!r}")
    try:
        number = int(value)
        exact = number == value
    except (TypeError, ValueError, OverflowError):
        exact = False
    if not exact:
        raise error(f"{what}: expected an integer, got {value!r}")
    if number < 0:
        raise error(f"{what}: expected a count >= 0, got {number}")
    top = limit(name)
    if number > top:
        spec = LIMITS[name]
        raise error(f"{what}: {number} is above the limit of {top} {spec.counts} (set {spec.env} to raise it)")
    return number


def check_bytes(nbytes: int, what: str, error: type[Exception] = InvalidArgumentError) -> int:
    """Refuse (``error``) an allocation of ``nbytes`` above the ``memory_mb`` limit, naming ``what`` and the fix."""
    top = limit("memory_mb")
    if nbytes > top * 2**20:
        spec = LIMITS["memory_mb"]
        raise error(f"{what} would take {nbytes / 2**20:,.0f} MB, above the limit of {top:,} MB for one allocation "
                    f"(set {spec.env} to raise it)")
    return int(nbytes)


__all__ = ["LIMITS", "Limit", "check_bytes", "check_count", "limit"]
