"""Bad input at the public perception entry points (saliency, interest points, load_object): each is refused with
the library's InvalidArgumentError naming the object or file and the problem, before any work is done, and the
docstrings say so. Good input next to each bad one gives a known answer."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from perception.errors import InvalidArgumentError, InvalidMeshError
from perception.loading import load_object
from perception.saliency import Saliency, saliency
from perception.shapes import make_object


@pytest.fixture(scope="module")
def box():
    return make_object("box", 0)


@pytest.fixture(scope="module")
def box_saliency(box):
    return saliency(box, "mesh")


def tetrahedron() -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_tetrahedron()


class TestInterestPoints:
    @pytest.mark.parametrize("n", [2.5, True, False, "3", None, 0, -1])
    def test_a_count_that_is_not_a_positive_integer_is_refused_first(self, box_saliency, n):
        """The message is about n itself, not about candidates (the box has thousands of them)."""
        with pytest.raises(InvalidArgumentError, match=r"box/0: n \(interest points\) must be an integer >= 1") as info:
            box_saliency.interest_points(n)
        assert "candidates" not in str(info.value)

    def test_an_integral_float_is_the_integer(self, box_saliency):
        np.testing.assert_array_equal(box_saliency.interest_points(3.0), box_saliency.interest_points(3))
        assert box_saliency.interest_points(np.int64(4)).shape == (4, 3)

    def test_more_points_than_candidates_names_the_candidates(self, box, box_saliency):
        n = box.n_vertices + 1  # the mesh method has no fixations: the candidates are the vertices
        with pytest.raises(InvalidArgumentError, match=f"cannot pick {n} interest points from {box.n_vertices} "):
            box_saliency.interest_points(n)

    @pytest.mark.parametrize("distance", [-1.0, math.nan, math.inf, "5", True])
    def test_a_bad_separation_is_refused(self, box_saliency, distance):
        with pytest.raises(InvalidArgumentError, match="min_distance_mm must be a finite number >= 0"):
            box_saliency.interest_points(3, min_distance_mm=distance)

    def test_the_docstring_names_the_error_raised(self):
        raises = Saliency.interest_points.__doc__.split("Raises:", 1)[1]
        assert "InvalidArgumentError" in raises and "SaliencyError" not in raises


class TestSaliencyArguments:
    @pytest.mark.parametrize("model, hint", [(None, "NoneType"), (tetrahedron(), "perception.load_object"),
                                             ("box.off", "perception.load_object")])
    def test_a_model_that_is_not_an_object_model_is_named(self, model, hint):
        with pytest.raises(InvalidArgumentError, match="saliency: expected a perception.ObjectModel") as info:
            saliency(model, "mesh")
        assert hint in str(info.value)

    def test_huge_weights_weigh_as_their_ratio(self, box):
        """Eq. 1 is a weighted mean: scaling every weight by the same factor changes nothing. Weights of 1e308
        overflowed their sum to inf and gave all-zero scores."""
        views = {"n_views": 4, "size_px": 32}
        unit = saliency(box, "multiview", weights={"intensity": 1.0, "contrast": 1.0}, **views)
        for scale in (1e308, 1e-300):
            scaled = saliency(box, "multiview", weights={"intensity": scale, "contrast": scale}, **views)
            assert scaled.scores.max() == 1.0
            np.testing.assert_allclose(scaled.scores, unit.scores, rtol=0, atol=1e-12)
        # 3:1 stays 3:1 at the top of the float range.
        ratio = saliency(box, "multiview", weights={"intensity": 3.0, "contrast": 1.0}, **views)
        huge = saliency(box, "multiview", weights={"intensity": 1.5e308, "contrast": 0.5e308}, **views)
        np.testing.assert_allclose(huge.scores, ratio.scores, rtol=0, atol=1e-12)

    @pytest.mark.parametrize("weights, match", [
        ({"intensity": "a"}, "finite numbers >= 0"),
        ({"intensity": 10**400}, "finite numbers >= 0"),
        ({"intensity": -1.0}, "finite numbers >= 0"),
        ({"intensity": True}, "finite numbers >= 0"),
        ([1.0, 2.0], "a dict of channel -> weight"),
    ])
    def test_bad_weights_are_refused_by_name(self, box, weights, match):
        with pytest.raises(InvalidArgumentError, match=f"box/0: .*{match}"):
            saliency(box, "multiview", weights=weights, n_views=4, size_px=32)

    def test_views_above_the_limit_are_refused_before_rendering(self, box):
        with pytest.raises(InvalidArgumentError, match="n_views: 1001 is above the limit of 1000 camera views"):
            saliency(box, "multiview", n_views=1001, size_px=8)


class TestLoadObjectSource:
    @pytest.mark.parametrize("source, match", [
        (np.zeros((3, 3)), "numpy array of shape \\(3, 3\\).*ObjectModel\\(vertices, triangles\\)"),
        (b"/tmp/cube.off", "a path must be text.*bytes b'/tmp/cube.off'.*os.fsdecode"),
        (None, "got NoneType None"),
        (42, "got int 42"),
    ])
    def test_a_source_that_is_neither_a_path_nor_a_mesh_is_named(self, source, match):
        with pytest.raises(InvalidArgumentError, match=f"load_object: .*{match}"):
            load_object(source)

    @pytest.mark.parametrize("key", ["name", "label"])
    def test_name_and_label_must_be_text(self, key):
        with pytest.raises(InvalidArgumentError, match=f"{key} must be text"):
            load_object(tetrahedron(), **{key: 5})


class TestLoadObjectArguments:
    @pytest.mark.parametrize("size_mm", [0, -5, math.nan, math.inf, "150", True, 1e13])
    def test_a_bad_size_is_an_argument_error(self, size_mm):
        with pytest.raises(InvalidArgumentError, match="open3d-mesh: size_mm must be a positive finite number") as info:
            load_object(tetrahedron(), size_mm=size_mm)
        assert not isinstance(info.value, InvalidMeshError)

    def test_arguments_are_checked_before_the_file_is_read(self, tmp_path):
        """A missing file with a bad size: the size is reported (a MeshLoadError would hide the typo)."""
        with pytest.raises(InvalidArgumentError, match="missing.off: size_mm"):
            load_object(tmp_path / "missing.off", size_mm=0)

    def test_a_good_size_scales_to_it(self):
        assert load_object(tetrahedron(), size_mm=40).size == pytest.approx(40.0)
        assert load_object(tetrahedron(), size_mm=np.float32(40)).size == pytest.approx(40.0)

    def test_an_unknown_centering_names_the_mesh_not_its_repr(self):
        with pytest.raises(InvalidArgumentError, match="^open3d-mesh: centering must be one of surface, bbox") as info:
            load_object(tetrahedron(), centering="foo")
        assert "TriangleMesh with" not in str(info.value)
        with pytest.raises(InvalidArgumentError, match="^cup: centering"):
            load_object(tetrahedron(), centering="foo", name="cup")

    @pytest.mark.parametrize("rotation, match", [
        (np.full((3, 3), np.nan), "rotation is not finite"),
        (np.diag([1.0, np.inf, 1.0]), "rotation is not finite"),
        ("x", "rotation must be a 3 x 3 matrix of numbers, got str 'x'"),
        ([["1", "0", "0"]] * 3, "rotation must be a 3 x 3 matrix of numbers"),
        ([[1, 0], [0, 1, 0]], "rotation must be a 3 x 3 matrix of numbers"),
        (np.eye(2), "rotation must be a 3 x 3 matrix, got shape \\(2, 2\\)"),
        (np.diag([1.0, 1.0, -1.0]), "rotation must be orthonormal with determinant \\+1 \\(a proper rotation\\)"),
    ])
    def test_a_bad_rotation_says_what_is_wrong(self, rotation, match):
        with pytest.raises(InvalidArgumentError, match=f"open3d-mesh: {match}"):
            load_object(tetrahedron(), rotation=rotation)

    def test_a_rotation_as_nested_lists_turns_the_vertices(self):
        quarter_turn = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 degrees about z: (x, y) -> (-y, x)
        mesh = tetrahedron()
        turned = load_object(mesh, rotation=quarter_turn, size_mm=None, repair=False, orient=False)
        v = np.asarray(mesh.vertices)
        np.testing.assert_array_equal(turned.vertices, np.stack([-v[:, 1], v[:, 0], v[:, 2]], axis=1))

    def test_the_docstring_lists_every_argument_error(self):
        raises = load_object.__doc__.split("Raises:", 1)[1].split("Examples:", 1)[0]
        for word in ("size_mm", "centering", "rotation", "source", "InvalidArgumentError"):
            assert word in raises, word
