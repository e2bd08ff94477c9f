"""Multi-touch fusion against hand-computed values; touch groups."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.decide import fuse_touches, touch_groups
from perception.errors import DatasetError, InvalidArgumentError


def test_sum_rule_averages_probabilities():
    np.testing.assert_allclose(fuse_touches([[0.6, 0.4], [0.3, 0.7]], "sum"), [0.45, 0.55])


def test_log_rule_multiplies_probabilities():
    # 0.6 * 0.3 = 0.18, 0.4 * 0.7 = 0.28 -> normalised by 0.46
    np.testing.assert_allclose(fuse_touches([[0.6, 0.4], [0.3, 0.7]], "log"), [0.18 / 0.46, 0.28 / 0.46])


def test_log_rule_lets_a_confident_touch_veto_but_stays_finite():
    fused = fuse_touches([[0.9, 0.1, 0.0], [0.0, 0.5, 0.5], [0.5, 0.5, 0.0]], "log")
    assert np.isfinite(fused).all() and fused.argmax() == 1 and fused[1] > 0.999
    # The sum rule instead prefers the class that is large twice.
    assert fuse_touches([[0.9, 0.1, 0.0], [0.0, 0.5, 0.5], [0.5, 0.5, 0.0]], "sum").argmax() == 0


def test_batched_groups_and_tiny_probabilities():
    proba = np.array([[[1e-300, 1.0], [1e-300, 1.0]], [[0.5, 0.5], [0.5, 0.5]]])
    fused = fuse_touches(proba, "log")
    assert fused.shape == (2, 2) and np.isfinite(fused).all()
    np.testing.assert_allclose(fused.sum(axis=1), 1.0)
    np.testing.assert_allclose(fused[1], [0.5, 0.5])


@pytest.mark.parametrize("bad", [[[np.nan, 1.0]], [[-0.1, 1.1]], [0.5, 0.5], np.zeros((1, 0))])
def test_bad_probabilities_are_refused(bad):
    with pytest.raises(DatasetError):
        fuse_touches(bad)


def test_unknown_rule_is_refused():
    with pytest.raises(InvalidArgumentError, match="unknown fusion rule"):
        fuse_touches([[1.0, 0.0]], "max")


def test_touch_groups_hold_distinct_sequences_of_one_object():
    object_ids = np.repeat([3, 5, 8], [7, 4, 2])
    groups = touch_groups(object_ids, 3, seed=1)
    # 7 // 3 + 4 // 3 + 2 // 3 = 3 groups
    assert groups.shape == (3, 3)
    for group in groups:
        assert len(set(group)) == 3 and len(set(object_ids[group])) == 1
    np.testing.assert_array_equal(touch_groups(object_ids, 3, seed=1), groups)
    assert len(touch_groups(object_ids, 2, seed=0, repeats=4)) == 4 * (3 + 2 + 1)


def test_touch_groups_refuse_impossible_requests():
    with pytest.raises(DatasetError, match="no object has 5"):
        touch_groups([0, 0, 1], 5)
    with pytest.raises(InvalidArgumentError, match="positive integer"):
        touch_groups([0, 0, 1], 0)
