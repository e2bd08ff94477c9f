"""Saliency: known answers on a rounded cube, channel bookkeeping, normalisation, learned weights."""

from __future__ import annotations

import types

import numpy as np
import open3d as o3d
import pytest

from perception import channels, primitives
from perception.channels import COLOR_CHANNELS, GEOMETRY_CHANNELS, itti_normalize
from perception.errors import InvalidArgumentError, SaliencyError
from perception.geometry import ObjectModel, load_object
from perception.mesh_saliency import iss_keypoints, neighbourhood_sums
from perception.saliency import METHODS, fit_channel_weights, load_marked_points, saliency

SIDE_MM, ROUND_MM = 80.0, 8.0


def rounded_cube(side_mm: float = SIDE_MM, radius_mm: float = ROUND_MM, subdivisions: int = 5) -> ObjectModel:
    """A cube with edges and corners rounded to ``radius_mm``: the points at distance ``radius_mm`` from an
    inner box, made by pushing a subdivided cube's vertices out from that box. Faces are flat, edges are
    quarter cylinders, corners are sphere octants."""
    box = o3d.geometry.TriangleMesh.create_box(side_mm, side_mm, side_mm).translate((-side_mm / 2,) * 3)
    box = box.subdivide_midpoint(subdivisions)
    p = np.asarray(box.vertices)
    inner = np.clip(p, -(side_mm / 2 - radius_mm), side_mm / 2 - radius_mm)
    out = p - inner
    vertices = inner + radius_mm * out / np.linalg.norm(out, axis=1, keepdims=True)
    return ObjectModel(vertices, np.asarray(box.triangles), name="rounded_cube")


def _regions(model: ObjectModel):
    """Vertex masks: corners (three coordinates in the rounded band), edges (two), face centres."""
    rounded = np.abs(model.vertices) > SIDE_MM / 2 - ROUND_MM + 1e-6
    central = np.abs(model.vertices) < SIDE_MM / 5
    return rounded.sum(1) == 3, rounded.sum(1) == 2, central.sum(1) == 2


@pytest.fixture(scope="module")
def cube() -> ObjectModel:
    return rounded_cube()


@pytest.fixture(scope="module")
def cube_saliency(cube):
    return {method: saliency(cube, method) for method in METHODS}


@pytest.mark.parametrize("method", METHODS)
def test_rounded_cube_corners_and_edges_beat_face_centres(cube, cube_saliency, method):
    sal = cube_saliency[method]
    corner, edge, face = _regions(cube)
    assert corner.sum() > 50 and edge.sum() > 500 and face.sum() > 500
    assert sal.scores.shape == (cube.n_vertices,)
    assert np.isfinite(sal.scores).all() and sal.scores.min() >= 0 and sal.scores.max() == pytest.approx(1.0)
    face_mean = sal.scores[face].mean()
    assert sal.scores[corner].mean() > 3 * face_mean + 0.05
    assert sal.scores[edge].mean() > 3 * face_mean + 0.05


@pytest.mark.parametrize("method", METHODS)
def test_interest_points_lie_on_the_surface_on_rounded_features_and_spread(cube, cube_saliency, method):
    points = cube_saliency[method].interest_points(8)
    assert points.shape == (8, 3)
    _, distance = cube.closest_points(points)
    assert distance.max() < 1e-3 * cube.diagonal
    # Every point on an edge or corner band: at least two coordinates within 4 mm of the rounded zone.
    band = (np.abs(points) > SIDE_MM / 2 - ROUND_MM - 4.0).sum(axis=1) >= 2
    assert band.all(), points
    separation = np.linalg.norm(points[:, None] - points[None], axis=2) + 1e9 * np.eye(8)
    assert separation.min() >= 0.1 * cube.diagonal - 1e-9


def test_multiview_interest_points_are_the_eight_corners(cube_saliency):
    points = cube_saliency["multiview"].interest_points(8)
    octants = {tuple(np.sign(p).astype(int)) for p in points}
    assert len(octants) == 8
    assert (np.abs(points) > SIDE_MM / 2 - ROUND_MM - 2.0).all()


def test_interest_points_on_a_real_mesh_lie_on_the_surface(shrec07):
    model = load_object(shrec07 / "Chair" / "101.off")
    for method in METHODS:
        points = saliency(model, method).interest_points(10)
        _, distance = model.closest_points(points)
        assert distance.max() < 1e-3 * model.diagonal, method


def test_interest_points_relax_the_separation_and_validate(cube_saliency):
    sal = cube_saliency["mesh"]
    # 60 points cannot be 15 mm apart on this cube: the distance is halved until they fit.
    assert len(np.unique(sal.interest_points(60), axis=0)) == 60
    with pytest.raises(InvalidArgumentError):
        sal.interest_points(0)
    with pytest.raises(InvalidArgumentError):
        sal.interest_points(10**7)
    with pytest.raises(InvalidArgumentError):
        sal.interest_points(3, min_distance_mm=-1.0)


def test_no_colour_channel_is_evaluated_without_colours(cube, monkeypatch):
    calls = {"color_opponency": 0, "dkl": 0}

    def counting(name, original):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return original(*args, **kwargs)

        return wrapper

    monkeypatch.setattr(channels, "_color_opponency", counting("color_opponency", channels._color_opponency))
    monkeypatch.setattr(channels, "_dkl", counting("dkl", channels._dkl))
    small = rounded_cube(subdivisions=3)
    sal = saliency(small, n_views=4, size_px=32)
    assert calls == {"color_opponency": 0, "dkl": 0}
    assert sal.channels_computed == GEOMETRY_CHANNELS
    assert set(sal.channels_skipped) == set(COLOR_CHANNELS)
    assert set(sal.channel_maps) == set(GEOMETRY_CHANNELS)

    coloured = ObjectModel(
        small.vertices, small.triangles, name="coloured", vertex_colors=np.full((small.n_vertices, 3), 0.5)
    )
    sal = saliency(coloured, n_views=4, size_px=32)
    assert calls == {"color_opponency": 1, "dkl": 1}
    assert sal.channels_computed == GEOMETRY_CHANNELS + COLOR_CHANNELS and not sal.channels_skipped


def test_colour_channels_peak_at_a_colour_boundary():
    # A sphere red on one side, green on the other: geometry is uniform, so colour contrast is only at x = 0.
    sphere = primitives.sphere(50.0, 4)
    colors = np.where(sphere.vertices[:, [0]] > 0, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    model = ObjectModel(sphere.vertices, sphere.triangles, name="two-tone", vertex_colors=colors)
    sal = saliency(model, n_views=12, size_px=96)
    x = np.abs(model.vertices[:, 0])
    for name in COLOR_CHANNELS:
        values = sal.channel_maps[name]
        assert values[x < 5].mean() > 5 * values[x > 25].mean(), name


def test_single_weight_reproduces_that_channel(cube):
    small = rounded_cube(subdivisions=3)
    sal = saliency(small, weights={"curvature": 1.0}, n_views=6, size_px=48)
    np.testing.assert_allclose(sal.scores, sal.channel_maps["curvature"], atol=1e-12)
    assert sal.weights["curvature"] == 1.0 and sal.weights["edges"] == 0.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"method": "nope"},
        {"weights": {"bogus": 1.0}},
        {"weights": {"edges": -1.0}},
        {"weights": {"dkl": 1.0}},
    ],
)
def test_bad_requests_are_invalid_arguments_naming_the_object(cube, kwargs):
    with pytest.raises(InvalidArgumentError, match="rounded_cube"):
        saliency(cube, **kwargs)


@pytest.mark.parametrize("method", METHODS)
def test_deterministic_and_finite_on_awkward_meshes(method):
    for model in (primitives.hollow_hemisphere(n_around=48, n_polar=24), primitives.plane(60.0, 15)):
        first = saliency(model, method, n_views=8, size_px=48)
        second = saliency(model, method, n_views=8, size_px=48)
        assert first.scores.tobytes() == second.scores.tobytes()
        assert np.isfinite(first.scores).all() and (first.scores >= 0).all() and (first.scores <= 1).all()


def test_itti_normalisation_promotes_a_single_peak():
    one = np.zeros((1, 21, 21))
    one[0, 10, 10] = 4.0
    two = one.copy()
    two[0, 3, 3] = 2.0
    assert itti_normalize(one).max() == pytest.approx(1.0)
    # Peaks 1 and 0.5 after scaling: factor (1 - 0.5)^2.
    assert itti_normalize(two).max() == pytest.approx(0.25)
    assert not itti_normalize(np.zeros((2, 5, 5))).any()


def test_gaussian_means_of_a_constant_are_that_constant():
    values = np.full(4, 2.5)
    vertices = np.array([[0.0, 0, 0], [0.5, 0, 0], [1.5, 0, 0], [4.5, 0, 0]])
    num, den = neighbourhood_sums(values, vertices, [1.0])
    np.testing.assert_allclose(num / den, 2.5)


def test_iss_keypoints_are_vertex_indices(cube):
    index = iss_keypoints(cube)
    assert len(index) > 0 and index.min() >= 0 and index.max() < cube.n_vertices
    assert np.array_equal(index, iss_keypoints(cube))


def test_fit_channel_weights_against_hand_computed_auc(monkeypatch):
    """Channel maps made by hand, so each channel's ROC area is known: the weights are 2 AUC - 1 (clipped
    at 0), averaged over the models, normalised to sum 1."""
    import perception.saliency as saliency_module

    models = [rounded_cube(subdivisions=2), primitives.torus(40.0, 15.0, 24, 12)]
    marked = [np.arange(0, m.n_vertices, 10) for m in models]  # every tenth vertex is "marked"
    rng = np.random.default_rng(0)
    maps = []
    for model, index in zip(models, marked, strict=True):
        positive = np.zeros(model.n_vertices, bool)
        positive[index] = True
        negatives = np.flatnonzero(~positive)
        below = rng.permutation(negatives)[: len(negatives) * 3 // 4]  # 3/4 of the negatives below the marks
        curvature_map = np.full(model.n_vertices, 2.0)
        curvature_map[positive], curvature_map[below] = 1.0, 0.0
        maps.append(
            {
                "intensity": positive + 0.001 * rng.random(model.n_vertices),  # AUC 1
                "contrast": np.ones(model.n_vertices),  # all ties: AUC 1/2
                "orientation": (~positive).astype(float),  # AUC 0
                "curvature": curvature_map,  # AUC = fraction of negatives below = len(below) / len(negatives)
                "edges": rng.random(model.n_vertices),
                "entropy": np.zeros(model.n_vertices),
                "symmetry": np.zeros(model.n_vertices),
            }
        )
        maps[-1]["auc_curvature"] = len(below) / len(negatives)
        maps[-1]["positive"] = positive

    calls = iter(maps)

    def fake_saliency(model, method, **kwargs):
        return types.SimpleNamespace(channel_maps={k: v for k, v in next(calls).items() if k in GEOMETRY_CHANNELS})

    monkeypatch.setattr(saliency_module, "saliency", fake_saliency)
    # radius 0: exactly the marked vertices are positive.
    weights = fit_channel_weights(models, [m.vertices[i] for m, i in zip(models, marked, strict=True)], radius_mm=0.0)
    d_curvature = 2 * np.mean([m["auc_curvature"] for m in maps]) - 1
    # Random "edges": its AUC by the rank formula, computed here independently with pairwise comparisons.
    auc_edges = np.mean(
        [
            np.mean(m["edges"][m["positive"]][:, None] > m["edges"][~m["positive"]][None, :])
            for m in maps
        ]
    )
    d_edges = max(2 * auc_edges - 1, 0.0)
    total = 1.0 + d_curvature + d_edges
    assert weights["intensity"] == pytest.approx(1.0 / total)
    assert weights["curvature"] == pytest.approx(d_curvature / total)
    assert weights["edges"] == pytest.approx(d_edges / total)
    for name in ("contrast", "orientation", "entropy", "symmetry"):
        assert weights[name] == 0.0
    with pytest.raises(SaliencyError):
        fit_channel_weights(models[:1], [])


def test_marked_points_file(tmp_path):
    good = tmp_path / "marks.txt"
    good.write_text("# x y z in mm\n1 2 3\n\n4.5, 5, -6  # trailing comment\n")
    np.testing.assert_array_equal(load_marked_points(good), [[1, 2, 3], [4.5, 5, -6]])
    cases = {
        "short.txt": "1 2\n",
        "nan.txt": "1 2 nan\n",
        "word.txt": "1 two 3\n",
        "empty.txt": "# nothing\n",
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(SaliencyError, match=name):
            load_marked_points(tmp_path / name)
    with pytest.raises(SaliencyError, match="missing.txt"):
        load_marked_points(tmp_path / "missing.txt")
