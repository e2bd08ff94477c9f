"""Small argument checks shared by the public functions, each raising a project exception that names the
object and the problem (numpy's own errors, e.g. for a negative seed, name neither)."""

from __future__ import annotations

import math
from numbers import Integral, Real

import numpy as np

from perception.errors import InvalidArgumentError, VisuotactileError


def check_seed(
    seed, where: str, error: type[VisuotactileError] = InvalidArgumentError, *, allow_none: bool = True
) -> int | np.random.Generator | None:
    """``seed`` if it is a non-negative integer, a ``numpy.random.Generator`` or (if allowed) None.

    Raises:
        error: anything else (negative, float, bool, string), naming ``where``.
    """
    if isinstance(seed, np.random.Generator) or (seed is None and allow_none):
        return seed
    if isinstance(seed, Integral) and not isinstance(seed, bool) and int(seed) >= 0:
        return int(seed)
    raise error(f"{where}: seed must be a non-negative integer or a numpy Generator, got {seed!r}")


def check_count(
    value, name: str, where: str, error: type[VisuotactileError] = InvalidArgumentError, *, minimum: int = 1
) -> int:
    """``value`` as an int if it is an integer (or an integral float) >= ``minimum``.

    Raises:
        error: a fraction (2.5), a bool, a non-number, or a value below ``minimum``, naming ``where``.
    """
    ok = isinstance(value, Integral) and not isinstance(value, bool)
    if not ok and isinstance(value, float) and np.isfinite(value) and value == int(value):
        ok = True
    if not ok or int(value) < minimum:
        raise error(f"{where}: {name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_length(value, name: str, where: str, error: type[VisuotactileError] = InvalidArgumentError, *,
                 maximum: float = math.inf, unit: str = "mm") -> float:
    """``value`` as a float if it is a finite real number >= 0 and <= ``maximum`` (a length in ``unit``, or any
    non-negative amount with ``unit=""``; bools, strings and integers too large for a float are refused). -0.0 comes
    back as 0.0: NumPy's samplers refuse a negative zero scale ("scale < 0").

    Raises:
        error: anything else, naming ``where`` and ``name``.
    """
    try:
        ok = (isinstance(value, Real) and not isinstance(value, bool) and np.isfinite(float(value))
              and 0 <= value <= maximum)
    except OverflowError:  # a Python integer beyond the float range
        ok = False
    if not ok:
        bound = ">= 0" if maximum == math.inf else f"in [0, {maximum:g}]"
        raise error(f"{where}: {name} must be a finite number {bound}{' ' + unit if unit else ''}, got {value!r}")
    return float(value) + 0.0  # -0.0 + 0.0 is 0.0


def check_object_model(model, what: str):
    """``model`` if it is a :class:`~perception.geometry.ObjectModel`.

    Raises:
        InvalidArgumentError: anything else, naming what was given; an Open3D mesh or a file path is told to go
            through ``perception.load_object`` first.
    """
    from perception.geometry import ObjectModel  # geometry imports this module

    if isinstance(model, ObjectModel):
        return model
    kind = f"{type(model).__module__}.{type(model).__qualname__}".removeprefix("builtins.")
    hint = "" if model is None else "; load it with perception.load_object(...) first (a mesh file or an Open3D mesh)"
    raise InvalidArgumentError(f"{what}: expected a perception.ObjectModel, got {kind}{hint}")


__all__ = ["check_count", "check_object_model", "check_seed"]
