"""Hypothesis properties in two sizes: a few examples in ``make test``, many more in ``make test-slow``."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings

_QUIET = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]


def fast_and_slow(fast: int, slow: int, **strategies):
    """Decorator giving ``(fast_test, slow_test)``: the same body under ``given(**strategies)``, derandomized
    (the same examples on every run), with ``fast`` and ``slow`` examples; the second is marked slow."""

    def wrap(body):
        def variant(n: int):
            return settings(
                max_examples=n, deadline=None, derandomize=True, database=None, suppress_health_check=_QUIET
            )(given(**strategies)(body))

        return variant(fast), pytest.mark.slow(variant(slow))

    return wrap
