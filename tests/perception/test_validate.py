"""The shared argument checks: what each accepts, returned as plain Python values, and what it refuses by name."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.errors import InvalidArgumentError
from perception.validate import check_length


@pytest.mark.parametrize("value, expected", [(0, 0.0), (1.5, 1.5), (np.float32(0.25), 0.25), (np.int64(3), 3.0)])
def test_check_length_accepts_finite_non_negative_numbers(value, expected):
    out = check_length(value, "noise_mm", "here")
    assert out == expected and type(out) is float


@pytest.mark.parametrize("value", [-1e-12, float("nan"), float("inf"), np.float32("nan"), True, "1", None,
                                   10**400, [1.0]])
def test_check_length_refuses_the_rest_naming_where_and_what(value):
    with pytest.raises(InvalidArgumentError, match=r"^here: noise_mm must be a finite number >= 0 mm"):
        check_length(value, "noise_mm", "here")


@pytest.mark.parametrize("value", [-0.0, np.float64(-0.0), np.float32(-0.0)])
def test_check_length_gives_a_negative_zero_as_zero(value):
    """-0.0 passes (it is >= 0) and comes back as +0.0: numpy.random's normal(0, -0.0) raises "scale < 0"."""
    out = check_length(value, "noise_mm", "here")
    assert out == 0.0 and math.copysign(1.0, out) == 1.0 and type(out) is float
    np.random.default_rng(0).normal(0.0, out, 3)  # numpy takes it as a scale


def test_check_length_refuses_beyond_its_maximum_and_says_the_range():
    assert check_length(2.0, "side", "here", maximum=2.0) == 2.0  # the bound itself is allowed
    with pytest.raises(InvalidArgumentError, match=r"^here: side must be a finite number in \[0, 2\] mm, got 2.5"):
        check_length(2.5, "side", "here", maximum=2.0)


def test_check_length_of_a_unitless_amount_names_no_unit():
    with pytest.raises(InvalidArgumentError, match=r"^here: weight must be a finite number >= 0, got -1$"):
        check_length(-1, "weight", "here", unit="")
