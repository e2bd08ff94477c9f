"""The pose-free object frame: centre and size that a rotation of the source mesh does not change, against
hand-computed answers (cube, a two-triangle sheet, an L of two boxes) and against rotated copies."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perception.errors import InvalidArgumentError
from perception.geometry import (
    ObjectModel,
    load_object,
    normalize,
    random_rotation,
    rescale,
    rotate,
    surface_centroid,
)
from perception.shapes import make_object

_CUBE_TRIANGLES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                            [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def box(sides) -> ObjectModel:
    """An axis-aligned box with the given side lengths, centred on the origin (8 vertices, 12 triangles)."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    return ObjectModel((corners - 0.5) * np.asarray(sides, float), _CUBE_TRIANGLES, name="box")


def write_off(path, vertices, triangles):
    lines = ["OFF", f"{len(vertices)} {len(triangles)} 0"]
    lines += [" ".join(f"{x:.17g}" for x in v) for v in vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in t) for t in triangles]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def hammer_file(tmp_path_factory):
    """An asymmetric closed mesh (a catalogue hammer) stored off-centre, at another scale, as an OFF file."""
    model = make_object("hammer", 2)
    raw = model.vertices * 0.37 + np.array([12.0, -40.0, 7.5])
    return write_off(tmp_path_factory.mktemp("pose") / "hammer.off", raw, model.triangles)


class TestSurfaceCentroid:
    def test_cube_centroid_is_its_centre(self):
        cube = box((2.0, 4.0, 6.0))
        np.testing.assert_allclose(surface_centroid(cube.vertices, cube.triangles), [0, 0, 0], atol=1e-12)

    def test_two_triangles_weighted_by_area(self):
        # A unit right triangle (area 1/2, centroid (1/3, 1/3, 0)) and one of area 2 (centroid (10 + 2/3, 2/3, 0)).
        vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [12, 0, 0], [10, 2, 0]], float)
        triangles = np.array([[0, 1, 2], [3, 4, 5]])
        expected = (0.5 * np.array([1 / 3, 1 / 3, 0]) + 2.0 * np.array([10 + 2 / 3, 2 / 3, 0])) / 2.5
        np.testing.assert_allclose(surface_centroid(vertices, triangles), expected, rtol=1e-14)

    def test_ignores_tessellation_density(self):
        """A unit square: the left half as two triangles, the right half as a fan of 40 around its centre. The
        mean vertex moves right; the area-weighted centroid stays at the square's centre."""
        left = np.array([[0, 0, 0], [0.5, 0, 0], [0.5, 1, 0], [0, 1, 0]], float)
        t = np.linspace(0, 1, 11)[:-1]
        ring = np.vstack([np.c_[0.5 + 0.5 * t, 0 * t], np.c_[1 + 0 * t, t], np.c_[1 - 0.5 * t, 1 + 0 * t],
                          np.c_[0.5 + 0 * t, 1 - t]])
        ring = np.c_[ring, np.zeros(len(ring))]
        vertices = np.vstack([left, [[0.75, 0.5, 0]], ring])
        fan = [[4, 5 + i, 5 + (i + 1) % len(ring)] for i in range(len(ring))]
        triangles = np.array([[0, 1, 2], [0, 2, 3], *fan])
        np.testing.assert_allclose(surface_centroid(vertices, triangles), [0.5, 0.5, 0], atol=1e-14)
        assert vertices.mean(axis=0)[0] > 0.65

    def test_no_area_falls_back_to_mean_vertex(self):
        vertices = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)
        np.testing.assert_allclose(surface_centroid(vertices, np.array([[0, 1, 2]])), [1, 0, 0])


class TestNormalize:
    def test_cube_known_size(self):
        """A cube's enclosing sphere about its centre has the space diagonal as diameter: a cube of side s
        loaded to 150 mm has side 150 / sqrt(3), whatever its pose."""
        cube = box((1.0, 1.0, 1.0))
        for seed in (0, 1, 2):
            turned = cube.vertices @ random_rotation(seed).T + 5.0
            out, _ = normalize(turned, 150.0, triangles=cube.triangles)
            np.testing.assert_allclose(np.linalg.norm(out, axis=1), 75.0, rtol=1e-12)
            edges = np.linalg.norm(out[cube.edges[:, 0]] - out[cube.edges[:, 1]], axis=1)
            assert edges.min() == pytest.approx(150.0 / np.sqrt(3), rel=1e-12)

    def test_bbox_mode_is_the_papers_frame(self):
        """An L of two boxes: the bounding-box centre and diagonal differ from the surface frame."""
        vertices = np.vstack([box((40, 10, 10)).vertices + [20, 5, 5], box((10, 30, 10)).vertices + [5, 25, 5]])
        triangles = np.vstack([box((1, 1, 1)).triangles, box((1, 1, 1)).triangles + 8])
        out, _ = normalize(vertices, 100.0, triangles=triangles, centering="bbox")
        lo, hi = out.min(axis=0), out.max(axis=0)
        np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
        assert np.linalg.norm(hi - lo) == pytest.approx(100.0)
        surface, _ = normalize(vertices, 100.0, triangles=triangles)
        np.testing.assert_allclose(surface_centroid(surface, triangles), 0, atol=1e-12)
        assert 2 * np.linalg.norm(surface, axis=1).max() == pytest.approx(100.0)

    def test_transform_maps_source_to_model(self, hammer_file):
        model = load_object(hammer_file)
        raw = make_object("hammer", 2).vertices * 0.37 + np.array([12.0, -40.0, 7.5])
        mapped = raw @ model.transform[:3, :3].T + model.transform[:3, 3]
        np.testing.assert_allclose(mapped, model.vertices, atol=1e-9)

    def test_unknown_centering(self):
        with pytest.raises(InvalidArgumentError, match="centering"):
            normalize(np.eye(3), centering="middle")


class TestPoseFreeLoading:
    @settings(max_examples=8, deadline=None)
    @given(seed=st.integers(0, 2**32 - 1))
    def test_rotation_before_loading_changes_neither_centre_nor_size(self, hammer_file, seed):
        """A mesh and any rotation of it (applied to the raw file's coordinates) load to the same centre and
        scale to 1e-6 of the size: the rotated load is the upright load turned by the same rotation."""
        upright = load_object(hammer_file)
        rotation = random_rotation(seed)
        turned = load_object(hammer_file, rotation=rotation)
        tolerance = 1e-6 * upright.size
        assert turned.size == pytest.approx(upright.size, abs=tolerance)
        np.testing.assert_allclose(turned.center, 0, atol=tolerance)
        np.testing.assert_allclose(turned.vertices, upright.vertices @ rotation.T, atol=tolerance)
        np.testing.assert_allclose(turned.principal_frame, rotation @ upright.principal_frame, atol=1e-6)

    def test_bounding_box_frame_depends_on_pose(self, hammer_file):
        """The paper's frame, for contrast: the same rotation changes its centre and scale."""
        upright = load_object(hammer_file, centering="bbox")
        turned = load_object(hammer_file, centering="bbox", rotation=random_rotation(3))
        scale = lambda m: np.linalg.norm(m.transform[:3, 0])
        assert abs(scale(turned) / scale(upright) - 1) > 1e-3

    def test_bad_rotation_is_refused(self, hammer_file):
        with pytest.raises(InvalidArgumentError, match="proper rotation"):
            load_object(hammer_file, rotation=np.diag([1.0, 1.0, -1.0]))
        with pytest.raises(InvalidArgumentError, match="3 x 3"):
            load_object(hammer_file, rotation=np.eye(2))

    def test_rotate_keeps_centre_and_records_the_turn(self):
        mug = make_object("mug", 1)
        rotation = random_rotation(9)
        turned = rotate(mug, rotation)
        np.testing.assert_allclose(turned.center, mug.center, atol=1e-9)
        assert turned.size == pytest.approx(mug.size, rel=1e-12)
        np.testing.assert_allclose(turned.transform[:3, :3], rotation @ mug.transform[:3, :3], atol=1e-12)

    def test_rescale_brings_a_capture_to_the_training_size(self):
        """A 40 mm box (physical size, off the origin) rescaled to 150 mm: centred, enclosing diameter 150."""
        small = box((40.0, 20.0, 10.0))
        small = ObjectModel(small.vertices + [300.0, 0, 50.0], small.triangles, name="capture")
        out = rescale(small)
        np.testing.assert_allclose(out.center, 0, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(out.vertices, axis=1), 75.0, rtol=1e-12)  # every corner
        mapped = small.vertices @ out.transform[:3, :3].T + out.transform[:3, 3]
        np.testing.assert_allclose(mapped, out.vertices, atol=1e-9)

    def test_random_rotation_is_seeded_and_proper(self):
        a, b = random_rotation(4), random_rotation(4)
        assert a.tobytes() == b.tobytes()
        np.testing.assert_allclose(a @ a.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(a) == pytest.approx(1.0)

    def test_centering_is_validated_on_the_model(self):
        with pytest.raises(InvalidArgumentError, match="centering"):
            ObjectModel(np.eye(3), np.array([[0, 1, 2]]), centering="nowhere")


class TestSaliencyIgnoresThePose:
    """The same mesh turned by a random rotation gets the same saliency: ISS picked other keypoints (about half of
    them) where a regular mesh's exact ties were broken by rotation rounding; mesh saliency's plateaus (a mug's side)
    changed which vertices were local maxima and so its normalisation, by up to 0.09."""

    @pytest.mark.parametrize("name, seed", [
        ("box", 0), ("mug", 0),
        pytest.param("can", 1, marks=pytest.mark.xfail(strict=True, reason=(
            "a solid of revolution has no unique principal frame: turned, its pose-free frame turns about the axis, "
            "the rounded vertices differ and the ties break otherwise (56-82 of 64-78 keypoints differ)"))),
    ])
    def test_iss_keypoints_are_the_same_in_any_pose(self, name, seed):
        from perception.geometry import random_rotation, rotate
        from perception.mesh_saliency import iss_keypoints

        model = make_object(name, seed)
        upright = iss_keypoints(model)
        assert len(upright) > 0
        for k in range(3):
            np.testing.assert_array_equal(iss_keypoints(rotate(model, random_rotation(k))), upright)

    @pytest.mark.parametrize("name, seed", [("mug", 0), ("can", 1)])
    def test_mesh_saliency_is_the_same_in_any_pose(self, name, seed):
        from perception.geometry import random_rotation, rotate
        from perception.saliency import saliency

        model = make_object(name, seed)
        upright = saliency(model, "mesh").scores
        for k in range(3):
            turned = saliency(rotate(model, random_rotation(k)), "mesh").scores
            assert np.abs(turned - upright).max() < 1e-4
