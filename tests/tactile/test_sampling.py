"""Contour sampling: blind never looks, guided planes pass through interest points, exploration is seeded."""

from __future__ import annotations

import numpy as np
import pytest

import perception.saliency as attention
from perception import primitives
from perception.errors import ContourError, InvalidArgumentError, SaliencyError
from perception.geometry import ObjectModel
from perception.shapes import make_object
from tactile import sampling, touching
from tactile.contours import make_contour
from tactile.sampling import INTEREST_POOL, MAX_DRAWS, sample_planes
from tactile.sensor import FSRSensor
from tactile.touching import Toucher, explore_object
from tests.perception.test_saliency import rounded_cube


@pytest.fixture(scope="module")
def cube() -> ObjectModel:
    return rounded_cube(subdivisions=4)


@pytest.fixture
def no_saliency(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("saliency was computed")

    monkeypatch.setattr(attention, "saliency", refuse)


def _on_plane(points: np.ndarray, plane, tol: float) -> np.ndarray:
    return np.abs((points - plane.point) @ plane.normal) < tol


def test_blind_sampling_never_computes_saliency(cube, no_saliency):
    planes = sample_planes(cube, "blind", 6, seed=1)
    assert len(planes) == 6
    for plane in planes:
        np.testing.assert_allclose(plane.point, cube.center)
        # The plane holds the centre and (at least) two mesh vertices.
        assert _on_plane(cube.vertices, plane, 1e-9 * cube.diagonal).sum() >= 2
    sequences = explore_object(
        cube, "blind", n_contours=2, probes=5, seed=1, sensor=FSRSensor(rows=8, cols=8)
    )
    assert [s.strategy for s in sequences] == ["blind", "blind"]


def test_guided_planes_pass_through_two_interest_points(cube, monkeypatch):
    calls = []
    original = attention.saliency

    def counting(model, method="multiview", **kwargs):
        calls.append(method)
        return original(model, method, **kwargs)

    monkeypatch.setattr(attention, "saliency", counting)
    sal = original(cube, "multiview")
    interest = sal.interest_points(INTEREST_POOL)
    planes = sample_planes(cube, "guided", 8, seed=4)
    assert calls == ["multiview"]
    for plane in planes:
        assert _on_plane(interest, plane, 1e-9 * cube.diagonal).sum() >= 2
    assert len({tuple(np.round(p.normal, 9)) for p in planes}) > 1


@pytest.mark.parametrize(("strategy", "method"), [("guided", "multiview"), ("mesh", "mesh"), ("iss", "iss")])
def test_precomputed_saliency_is_reused_and_checked(cube, no_saliency, strategy, method):
    sal = attention.Saliency(cube, np.linspace(0, 1, cube.n_vertices), method)
    planes = sample_planes(cube, strategy, 3, seed=0, saliency=sal)
    interest = sal.interest_points(INTEREST_POOL)
    assert all(_on_plane(interest, p, 1e-9 * cube.diagonal).sum() >= 2 for p in planes)
    wrong = attention.Saliency(cube, sal.scores, "iss" if method != "iss" else "mesh")
    with pytest.raises(SaliencyError, match="rounded_cube"):
        sample_planes(cube, strategy, 3, saliency=wrong)


def fail_first(monkeypatch, name: str, times: int, message: str, module=sampling) -> dict:
    """Make ``module.<name>`` raise ContourError(message) on its first ``times`` calls; returns the
    counter of failures still to come."""
    original = getattr(module, name)
    left = {"left": times}

    def flaky(*args, **kwargs):
        if left["left"]:
            left["left"] -= 1
            raise ContourError(message)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, flaky)
    return left


def test_near_collinear_draws_are_redrawn_then_refused(cube, monkeypatch):
    failures = fail_first(monkeypatch, "plane_through", 5, "near-collinear")
    assert len(sample_planes(cube, "blind", 2, seed=0)) == 2
    assert failures["left"] == 0
    # A needle: every pair of its vertices is near-collinear with the centre, so the draws run out.
    z = np.linspace(-50, 50, 30)
    needle = ObjectModel(
        np.column_stack([np.tile([0.0, 1e-4], 15), np.zeros(30), z]),
        np.array([[i, i + 1, i + 2] for i in range(28)]),
        name="needle",
    )
    with pytest.raises(ContourError, match="near-collinear"):
        sample_planes(needle, "blind", 1, seed=0)


def test_planes_that_miss_are_redrawn(cube, monkeypatch):
    misses = fail_first(monkeypatch, "make_contour", 3, "misses the object", module=touching)
    sequences = explore_object(
        cube, "blind", n_contours=2, probes=6, seed=2, sensor=FSRSensor(rows=8, cols=8)
    )
    assert len(sequences) == 2 and misses["left"] == 0

    def always_miss(*args, **kwargs):
        raise ContourError("misses the object")

    monkeypatch.setattr(touching, "make_contour", always_miss)
    with pytest.raises(ContourError, match=str(MAX_DRAWS)):
        explore_object(cube, "blind", n_contours=1, seed=2)


def test_explore_object_is_seeded_and_records_strategy(cube):
    sal = attention.saliency(cube, "mesh")
    sensor = FSRSensor(rows=8, cols=8)
    first = explore_object(cube, "mesh", n_contours=3, sensor=sensor, probes=7, seed=11, saliency=sal)
    again = explore_object(cube, "mesh", n_contours=3, sensor=sensor, probes=7, seed=11, saliency=sal)
    other = explore_object(cube, "mesh", n_contours=3, sensor=sensor, probes=7, seed=12, saliency=sal)
    assert len(first) == 3
    for a, b in zip(first, again, strict=True):
        assert a.frames.tobytes() == b.frames.tobytes() and a.positions.tobytes() == b.positions.tobytes()
        assert a.strategy == "mesh" and a.seed == b.seed and isinstance(a.seed, int)
        assert a.frames.shape == (7, 8, 8) and a.object_name == "rounded_cube"
    assert any(a.positions.tobytes() != c.positions.tobytes() for a, c in zip(first, other, strict=True))


def test_bad_requests(cube):
    with pytest.raises(InvalidArgumentError, match="strategy"):
        sample_planes(cube, "psychic", 2)
    with pytest.raises(InvalidArgumentError):
        sample_planes(cube, "blind", 0)
    with pytest.raises(InvalidArgumentError):
        explore_object(cube, "blind", n_contours=0)
    with pytest.raises(InvalidArgumentError, match="probes"):
        explore_object(cube, "blind", probes=1)


def test_guided_exploration_on_a_primitive_touches_the_object():
    model = primitives.torus(40.0, 15.0, 48, 24)
    (seq,) = explore_object(model, "guided", n_contours=1, probes=9, seed=0, sensor=FSRSensor(rows=8, cols=8))
    _, distance = model.closest_points(seq.positions)
    assert distance.max() < 1e-3 * model.diagonal and seq.strategy == "guided"


def test_toucher_cuts_a_repeated_plane_once_and_draws_the_same(monkeypatch):
    """A Toucher cuts each distinct plane once; the contours drawn equal fresh cuts of the same draws."""
    model = make_object("mug", 2)
    points = model.vertices[[0, 50, 100]]  # 3 points: 6 ordered pairs, so 40 draws must repeat planes
    plain = []
    rng = np.random.default_rng(5)
    for _ in range(40):
        plain.append(make_contour(model, sampling.draw_plane(model, points, rng), 8))
    cuts = []
    original = touching.make_contour
    monkeypatch.setattr(touching, "make_contour", lambda *a, **k: cuts.append(a[1]) or original(*a, **k))
    toucher = Toucher(model, "blind", probes=8)
    toucher.points = points
    rng = np.random.default_rng(5)
    cached = [toucher.draw(rng) for _ in range(40)]
    assert len(cuts) <= 6
    assert len({id(c) for c in cached}) == len(cuts)
    for a, b in zip(plain, cached):
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.normals, b.normals)
