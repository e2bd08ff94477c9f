"""The information policy cuts each candidate plane once, on the smoothed visual model it presses (2026-12-07):
the planes are drawn through the visual model's centre and points as before, but no longer cut on the raw visual
model too. Tested against an independent re-implementation of the old draw and by counting cuts."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.active import ActiveState, make_policy, noisy_copy
from fusion.active.policies import smoothed
from perception.errors import ContourError, InvalidArgumentError
from perception.shapes import make_object
from tactile import sampling
from tactile.touching import Toucher
from tests.fusion.test_active import ConstantClassifier


@pytest.fixture(scope="module")
def visual():
    return noisy_copy(make_object("mug", 0), 0.5, seed=1)


def test_draw_cut_by_draws_the_same_planes_and_returns_the_other_cut(visual):
    raw = Toucher(visual, "blind")
    surface = Toucher(smoothed(visual, 10), "blind")
    for seed in range(5):
        mine = raw.draw(np.random.default_rng(seed))
        theirs = raw.draw(np.random.default_rng(seed), cut_by=surface)
        # the same draws of two points through the raw model's centre (every such plane cuts the mug)
        plane = sampling.draw_plane(visual, raw.points, np.random.default_rng(seed))
        assert np.array_equal(theirs.plane.normal, plane.normal) and np.array_equal(theirs.plane.point, plane.point)
        assert np.array_equal(mine.plane.normal, plane.normal)
        # the contour is the smoothed surface's: its probes lie on that surface, not the raw one
        assert np.array_equal(theirs.positions, surface.cut(plane).positions)
        assert not np.array_equal(theirs.positions, mine.positions)


def test_draw_cut_by_redraws_planes_that_miss_the_other_model():
    """A plane that cuts this model but misses ``cut_by``'s is drawn again (here every plane misses: far away)."""
    box = make_object("box", 0)
    far = Toucher(_shifted(box), "blind")
    with pytest.raises(ContourError, match="planes in a row missed"):
        Toucher(box, "blind").draw(np.random.default_rng(0), cut_by=far)
    with pytest.raises(InvalidArgumentError, match="cut_by must be a Toucher"):
        Toucher(box, "blind").draw(np.random.default_rng(0), cut_by="surface")


def _shifted(model):
    from perception.geometry import ObjectModel

    # a million mm off along a direction no plane through the near box's centre and two of its corners contains
    return ObjectModel(model.vertices + 1e6 * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0), model.triangles,
                       name="far box")


def test_the_information_policy_cuts_candidates_only_on_the_smoothed_model(visual, monkeypatch):
    cuts = []
    original = Toucher.cut

    def counting(self, plane):
        cuts.append(self.model.name)
        return original(self, plane)

    monkeypatch.setattr(Toucher, "cut", counting)
    policy = make_policy("information", 3, candidates=6, variants=2)
    state = ActiveState(visual, ConstantClassifier())
    planes = policy.candidate_planes(state)
    policy.simulated(state)
    assert len(planes) == 6
    assert not [name for name in cuts if not name.endswith("@smoothed")]  # never the raw visual model
    surface = policy._surface(state)
    assert len(surface._cuts) == 6  # each candidate cut once, its cut reused by both variants
