"""Touching in any pose: the same object-frame contour on a mesh and on a rotated copy of it (rotated before
loading) gives the same tactile frames and pose-free cues; the paper's normals cue turns with the object."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fusion.cues import INVARIANT_NAMES, kinesthetic_cues
from perception.errors import DatasetError
from perception.geometry import load_object, random_rotation
from perception.shapes import make_object
from tactile.contours import Plane, make_contour
from tactile.dataset.objects import ObjectSpec
from tactile.explore import SequenceBatch, explore
from tactile.sampling import explore_object

#: Cue channels in millimetres (compared to 1e-4 mm); the others are cosines (compared to 1e-6).
MM_CUES = [i for i, name in enumerate(INVARIANT_NAMES) if name.endswith("_mm")]
UNITLESS_CUES = [i for i in range(len(INVARIANT_NAMES)) if i not in MM_CUES]


@pytest.fixture(scope="module")
def bottle_file(tmp_path_factory):
    """An asymmetric catalogue object (a mug: handle on one side) written to OFF off-centre and rescaled."""
    model = make_object("mug", 4)
    raw = model.vertices * 2.5 - np.array([3.0, 70.0, 11.0])
    path = tmp_path_factory.mktemp("touch") / "mug.off"
    lines = ["OFF", f"{model.n_vertices} {model.n_triangles} 0"]
    lines += [" ".join(f"{x:.17g}" for x in v) for v in raw]
    lines += ["3 " + " ".join(map(str, t)) for t in model.triangles]
    path.write_text("\n".join(lines) + "\n")
    return path


def _sequence(model, normal):
    contour = make_contour(model, Plane(model.center, normal), 25)
    return explore(model, contour)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), normal_seed=st.integers(0, 2**32 - 1))
@example(seed=0, normal_seed=5)  # grazing taxels: 1.8e-4 mm apart when rays were cast in world coordinates
def test_frames_and_pose_free_cues_do_not_depend_on_the_pose(bottle_file, seed, normal_seed):
    upright = load_object(bottle_file)
    rotation = random_rotation(seed)
    turned = load_object(bottle_file, rotation=rotation)
    normal = np.random.default_rng(normal_seed).normal(size=3)
    a, b = _sequence(upright, normal), _sequence(turned, rotation @ normal)
    # The probes are the same surface points, turned.
    np.testing.assert_allclose(b.positions, a.positions @ rotation.T, atol=1e-6)
    np.testing.assert_allclose(b.frames, a.frames, atol=1e-4)  # mm of gap
    np.testing.assert_allclose(b.pad_sides_mm, a.pad_sides_mm, atol=1e-4)
    cues_a, cues_b = (kinesthetic_cues(SequenceBatch.from_sequences([s]), "invariant")[0] for s in (a, b))
    np.testing.assert_allclose(cues_b[:, MM_CUES], cues_a[:, MM_CUES], atol=1e-4)
    np.testing.assert_allclose(cues_b[:, UNITLESS_CUES], cues_a[:, UNITLESS_CUES], atol=1e-6)
    # The paper's cue is the normal in the object's frame: it turns with the object.
    np.testing.assert_allclose(b.normals, a.normals @ rotation.T, atol=1e-6)


def test_the_normals_cue_changes_with_the_pose(bottle_file):
    """Contrast for the test above: the same contour's normals cue differs by far more than its tolerance."""
    upright = load_object(bottle_file)
    rotation = random_rotation(1)
    turned = load_object(bottle_file, rotation=rotation)
    a, b = _sequence(upright, [0.3, 1.0, 0.2]), _sequence(turned, rotation @ np.array([0.3, 1.0, 0.2]))
    assert np.abs(b.normals - a.normals).max() > 0.1


def test_guided_contours_follow_the_object(bottle_file):
    """Guided sampling on a turned object draws the turned contours (saliency views live in the object's
    principal frame), so its sequences equal the upright ones."""
    rotation = random_rotation(5)
    upright, turned = load_object(bottle_file), load_object(bottle_file, rotation=rotation)
    a = explore_object(upright, "guided", n_contours=2, seed=3)
    b = explore_object(turned, "guided", n_contours=2, seed=3)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(y.positions, x.positions @ rotation.T, atol=1e-6)
        np.testing.assert_allclose(y.frames, x.frames, atol=1e-4)


def test_object_spec_presents_the_object_in_its_seeded_pose(bottle_file):
    spec = ObjectSpec("mug/4", "mug", path=str(bottle_file), rotation_seed=17)
    model = spec.load()
    expected = load_object(bottle_file, rotation=random_rotation(17))
    np.testing.assert_allclose(model.vertices, expected.vertices, atol=1e-12)
    assert spec.to_dict()["rotation_seed"] == 17 and "rotation_seed" not in ObjectSpec(
        "mug/4", "mug", path=str(bottle_file)).to_dict()
    for bad in (-1, 1.5, True, "7"):
        with pytest.raises(DatasetError, match="rotation_seed"):
            ObjectSpec("mug/4", "mug", path=str(bottle_file), rotation_seed=bad)
    catalogue = ObjectSpec("mug/4", "mug", catalogue=("mug", 4), rotation_seed=17).load()
    upright = make_object("mug", 4)
    np.testing.assert_allclose(catalogue.vertices, upright.vertices @ random_rotation(17).T, atol=1e-9)
