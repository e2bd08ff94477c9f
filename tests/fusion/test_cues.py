"""Kinesthetic cues against analytic circles on spheres, and their invariance under rigid motions."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.cues import INVARIANT_NAMES, cue_width, kinesthetic_cues
from perception.errors import InvalidArgumentError
from tests.fusion._synthetic import circle_batch, rotation


def test_invariant_cues_of_a_great_circle_are_the_analytic_values():
    radius, probes = 40.0, 12
    cues = kinesthetic_cues(circle_batch([radius], probes=probes), "invariant")
    assert cues.shape == (1, probes, len(INVARIANT_NAMES)) == (1, probes, cue_width("invariant"))
    named = dict(zip(INVARIANT_NAMES, np.moveaxis(cues[0], -1, 0)))
    np.testing.assert_allclose(named["radial_mm"], radius, rtol=1e-6)
    np.testing.assert_allclose(named["normal_out_of_plane"], 0.0, atol=1e-6)  # normal lies in the plane
    np.testing.assert_allclose(named["normal_radial"], 1.0, atol=1e-6)  # sphere normal is radial
    np.testing.assert_allclose(named["tangent_radial"], 0.0, atol=1e-6)  # a circle keeps its distance
    np.testing.assert_allclose(named["pad_side_mm"], 20.0)
    np.testing.assert_allclose(named["step_mm"], 2 * radius * np.sin(np.pi / probes), rtol=1e-6)  # chord


def test_invariant_cues_do_not_change_under_rotation_and_translation_but_normals_do():
    batch = circle_batch([30.0, 55.0], probes=10, seed=4)
    # Make the geometry less symmetric than a circle: stretch positions along one axis.
    batch.positions = (batch.positions * np.array([1.0, 1.7, 0.6])).astype(np.float32)
    moved = batch.subset(slice(None))
    turn, shift = rotation(7), np.array([120.0, -35.0, 9.0])
    for name in ("normals", "tangents"):
        setattr(moved, name, (getattr(batch, name) @ turn.T).astype(np.float32))
    moved.positions = (batch.positions @ turn.T + shift).astype(np.float32)
    moved.plane_points = batch.plane_points @ turn.T + shift
    moved.plane_normals = batch.plane_normals @ turn.T
    np.testing.assert_allclose(
        kinesthetic_cues(moved, "invariant"), kinesthetic_cues(batch, "invariant"), atol=2e-4
    )
    assert not np.allclose(kinesthetic_cues(moved, "normals"), kinesthetic_cues(batch, "normals"), atol=1e-2)


def test_a_probe_at_the_centre_gives_finite_cues():
    batch = circle_batch([10.0], probes=6)
    batch.positions[0, 0] = 0.0
    cues = kinesthetic_cues(batch, "invariant")
    assert np.isfinite(cues).all()
    assert cues[0, 0, INVARIANT_NAMES.index("normal_radial")] == 0.0


def test_unknown_cue_is_refused():
    with pytest.raises(InvalidArgumentError, match="unknown kinesthetic cue"):
        kinesthetic_cues(circle_batch([10.0]), "curvature")
