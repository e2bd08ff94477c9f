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
    with pytest.raises(ContourError, match="near-collinear with the centre .seen from its centre the object lies along one line: a needle"):
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


# ---------------------------------------------------------------------------- guided pairs without repeats
def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_pair_planes_are_the_distinct_planes_of_the_pairs():
    # Centre at the origin; four points: a, b, c in the z = 0 plane (coplanar with the centre: one plane for their
    # three pairs), d on the z axis (planes a-d, b-d, c-d: normals a x z, b x z, c x z), and e = -a (collinear
    # with a and the centre: a-e gives no plane, and b-e, c-e, d-e lie in the planes of b-a, c-a, d-a).
    model = ObjectModel(np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]]) * 40,
                        np.array([[0, 1, 2], [0, 2, 4], [1, 3, 2], [3, 4, 2], [0, 1, 5], [0, 5, 4], [1, 3, 5],
                                  [3, 4, 5]]), name="octahedron")
    assert np.allclose(model.center, 0)
    a, b, c, d = [40, 0, 0], [0, 40, 0], [-30, 30, 0], [0, 0, 40]
    points = np.array([a, b, c, d, [-40, 0, 0]], dtype=np.float64)
    planes = sampling.pair_planes(model, points)
    expected = [[0, 0, 1], np.cross(a, d), np.cross(b, d), np.cross(c, d)]
    assert len(planes) == 4
    for plane, normal in zip(planes, expected, strict=True):
        assert abs(abs(plane.normal @ _unit(normal)) - 1) < 1e-12
        np.testing.assert_array_equal(plane.point, model.center)
    # Within SAME_PLANE_DEG of an earlier plane is the same plane; just beyond it is another. Pairs of a, b and
    # x = b tilted about the x axis: a-b is z = 0, a-x that plane tilted (merged or not), b-x the x = 0 plane.
    tilt = np.radians(sampling.SAME_PLANE_DEG)
    for factor, count in ((0.9, 2), (1.1, 3)):
        x = [0, 40 * np.cos(factor * tilt), 40 * np.sin(factor * tilt)]
        assert len(sampling.pair_planes(model, np.array([a, b, x], dtype=np.float64))) == count


def test_pair_order_takes_every_plane_once_per_cycle():
    model = make_object("can", 1)
    points = model.vertices[np.random.default_rng(0).choice(model.n_vertices, 6, replace=False)]
    planes = sampling.pair_planes(model, points)
    order = sampling.PairOrder(planes, 123, "can/1")
    n = len(order)
    assert n == len(planes) > 5
    for cycle in range(3):
        ids = [id(order[k]) for k in range(cycle * n, (cycle + 1) * n)]
        assert sorted(ids) == sorted(id(p) for p in planes)
    # Position k depends on (seed, k) only: a fresh order gives the same planes in any reading order.
    fresh = sampling.PairOrder(planes, 123)
    assert [id(fresh[k]) for k in (2 * n + 1, 0, n)] == [id(order[k]) for k in (2 * n + 1, 0, n)]
    # Another seed, another order; the cycles differ from each other.
    other = sampling.PairOrder(planes, 124)
    assert [id(other[k]) for k in range(n)] != [id(order[k]) for k in range(n)]
    assert [id(order[k]) for k in range(n)] != [id(order[k]) for k in range(n, 2 * n)]
    with pytest.raises(ContourError, match="can/1"):
        sampling.PairOrder([], 0, "can/1")
    for bad in (-1, 2**63, 1.5, True):
        with pytest.raises(InvalidArgumentError, match="seed"):
            sampling.PairOrder(planes, bad)
    with pytest.raises(InvalidArgumentError, match="positions"):
        order[-1]


@pytest.mark.parametrize("seeding", ["stream", "object"])
def test_guided_touches_repeat_no_plane_until_all_are_used(seeding):
    model = make_object("mug", 3)
    sal = attention.saliency(model, "multiview")
    usable = Toucher(model, "guided", probes=6, saliency=sal).pair_order(0).planes
    contours: list = []
    explore_object(model, "guided", len(usable) + 3, FSRSensor(rows=4, cols=4), 6, seed=9, saliency=sal,
                   seeding=seeding, contours=contours)
    normals = np.array([c.plane.normal for c in contours])
    same = np.abs(normals @ normals.T) > np.cos(np.radians(sampling.SAME_PLANE_DEG))
    first = same[: len(usable), : len(usable)]
    assert (first == np.eye(len(usable), dtype=bool)).all()  # the first cycle: each usable plane once
    assert same[len(usable):, : len(usable)].sum(axis=1).tolist() == [1, 1, 1]  # then repeats begin
    # sample_planes (no cutting) does the same with the pairs that are not near-collinear.
    planes = sample_planes(model, "guided", 20, seed=3, saliency=sal)
    n = np.array([p.normal for p in planes])
    assert (np.abs(n @ n.T) > np.cos(np.radians(sampling.SAME_PLANE_DEG))).sum() == 20


# ------------------------------------------------------------- guided pairs: what the tests above leave open
def _octahedron() -> ObjectModel:
    return ObjectModel(np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]]) * 40,
                       np.array([[0, 1, 2], [0, 2, 4], [1, 3, 2], [3, 4, 2], [0, 1, 5], [0, 5, 4], [1, 3, 5],
                                 [3, 4, 5]]), name="octahedron")


def test_planes_within_one_degree_are_one_plane():
    # The threshold is one degree (the module's promise: 1.7 mm at 100 mm), in literal degrees, so that a change
    # of SAME_PLANE_DEG (which the test above reads back) is seen. a-b is z = 0, a-x that plane tilted by deg.
    model = _octahedron()
    a, b = [40, 0, 0], [0, 40, 0]
    for deg, count in ((0.5, 2), (0.95, 2), (1.05, 3), (2.0, 3), (5.0, 3)):
        x = [0, 40 * np.cos(np.radians(deg)), 40 * np.sin(np.radians(deg))]
        assert len(sampling.pair_planes(model, np.array([a, b, x], dtype=np.float64))) == count, deg


def test_pair_order_is_the_documented_permutation():
    # Position k is planes[perm_c[k % P]], perm_c the permutation of default_rng([seed, c]), c = k // P: stores
    # resumed by another version take the same rows only if this is kept exactly.
    model = make_object("can", 1)
    points = model.vertices[np.random.default_rng(0).choice(model.n_vertices, 6, replace=False)]
    planes = sampling.pair_planes(model, points)
    n = len(planes)
    for seed in (0, 2**40 + 7, 2**63 - 1):
        order = sampling.PairOrder(planes, seed)
        for k in range(3 * n):
            assert order[k] is planes[np.random.default_rng([seed, k // n]).permutation(n)[k % n]], (seed, k)


@pytest.fixture(scope="module")
def mug_guided():
    model = make_object("mug", 3)
    return model, attention.saliency(model, "multiview")


def test_guided_sample_planes_take_every_pair_from_the_first_and_follow_the_seed(mug_guided):
    model, sal = mug_guided
    pairs = sampling.pair_planes(model, sampling.candidates(model, "guided", sal))
    n = len(pairs)

    def keys(planes):
        return [min(p.normal.tobytes(), (-p.normal).tobytes()) for p in planes]

    runs = {seed: sample_planes(model, "guided", n + 2, seed=seed, saliency=sal) for seed in (0, 1, 2)}
    for planes in runs.values():
        assert sorted(keys(planes[:n])) == sorted(keys(pairs))  # the first n: every pair once
    assert keys(sample_planes(model, "guided", n + 2, seed=1, saliency=sal)) == keys(runs[1])  # same seed, same
    assert len({tuple(keys(p[:5])) for p in runs.values()}) == 3  # another seed, another order


def test_pair_order_leaves_out_pairs_whose_plane_misses(mug_guided, monkeypatch):
    model, sal = mug_guided
    toucher = Toucher(model, "guided", probes=6, saliency=sal)
    pairs = sampling.pair_planes(model, toucher.points)
    missing = {pairs[0].normal.tobytes(), pairs[3].normal.tobytes()}
    real_cut = toucher.cut

    def cut(plane):
        if np.asarray(plane.normal).tobytes() in missing:
            raise ContourError(f"{model.name}: the plane misses")
        return real_cut(plane)

    monkeypatch.setattr(toucher, "cut", cut)
    order = toucher.pair_order(5)
    assert len(order) == len(pairs) - 2
    assert not any(p.normal.tobytes() in missing for p in order.planes)
    touched = [p.contour.plane.normal.tobytes() for p in toucher.stream(len(pairs) + 3, 1)]
    assert not missing & set(touched)


def test_guided_object_seeding_follows_the_seed(mug_guided):
    model, sal = mug_guided
    toucher = Toucher(model, "guided", probes=6, saliency=sal)

    def normals(seed):
        return [p.contour.plane.normal.tobytes() for p in toucher.by_object(8, seed)[0]]

    assert normals(0) == normals(0)
    assert len({tuple(normals(seed)) for seed in (0, 1, 2)}) == 3


def test_pair_order_refuses_what_is_not_a_position_and_iterates_one_cycle():
    model = make_object("can", 1)
    planes = sampling.pair_planes(model, model.vertices[[0, 40, 80, 120]])
    order = sampling.PairOrder(np.array(planes, dtype=object), 3, "can/1")  # any sequence of planes
    assert len(list(order)) == len(planes) and all(any(p is q for q in planes) for p in order)
    assert planes[0] in order  # membership ends (one cycle)
    assert order[np.int64(2)] is order[2]
    for bad in (-1, 1.5, True, None, "a", float("nan"), float("inf"), slice(0, 2)):
        with pytest.raises(InvalidArgumentError, match="can/1"):
            order[bad]
    with pytest.raises(ContourError, match="can/1"):
        sampling.PairOrder(None, 0, "can/1")


def test_only_guided_strategies_have_a_pair_order(monkeypatch):
    model = make_object("mug", 3)
    monkeypatch.setattr(sampling, "pair_planes", lambda *a: pytest.fail("listed every vertex pair"))
    with pytest.raises(InvalidArgumentError, match="mug/3.*blind"):
        Toucher(model, "blind", probes=6).pair_order(0)
    toucher = Toucher(model, "blind", probes=6)
    with pytest.raises(InvalidArgumentError, match="start"):
        next(toucher.stream(1, 0, start=1.5))


def test_pair_setting_reads_one_name_or_several_and_refuses_unknown_ones():
    assert sampling.pair_setting("guided") == sampling.pair_setting(["blind", "mesh"]) == {"guided_pairs": "without repeats"}
    assert sampling.pair_setting("blind") == sampling.pair_setting(("blind",)) == {}
    with pytest.raises(InvalidArgumentError, match="bogus"):
        sampling.pair_setting(["blind", "bogus"])


def test_toucher_keeps_its_last_pair_order_and_checks_every_seed(mug_guided):
    model, sal = mug_guided
    toucher = Toucher(model, "guided", probes=6, saliency=sal)
    first = toucher.pair_order(7)
    assert toucher.pair_order(7) is first and toucher.pair_order(np.int64(7)) is first
    fresh = sampling.PairOrder(first.planes, 7, model.name)
    assert [p.normal.tobytes() for p in first] == [p.normal.tobytes() for p in fresh]
    other = toucher.pair_order(8)
    assert other is not first and other.seed == 8 and toucher.pair_order(8) is other
    assert [p.normal.tobytes() for p in toucher.pair_order(7)] == [p.normal.tobytes() for p in fresh]
    for bad in (-1, True, 2**63, 7.0, [7]):
        with pytest.raises(InvalidArgumentError, match="seed"):
            toucher.pair_order(bad)
