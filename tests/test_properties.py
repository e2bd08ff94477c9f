"""Properties across the pipeline (hypothesis): generated meshes (catalogue objects, random convex
hulls, analytic primitives, each under a random rotation, scale and shift), cutting planes, sensor specs,
tactile sequences and fitted classifiers. Whatever is drawn, only documented exceptions (VisuotactileError)
come out, no output holds NaN or Inf, and the invariants hold: probes on the surface and in their plane,
unit normals and tangents, readings within their range, pad sides on the sensor's ladder, probabilities in
[0, 1] summing to 1, curvature finite and covariant under similarity transforms."""

from __future__ import annotations

import dataclasses
import json
from functools import cache

import numpy as np
import pytest
import trimesh
from hypothesis import assume, event
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from fusion.classifiers import make_classifier
from perception import primitives
from perception.curvature import compute_curvature
from perception.errors import SensorSpecError, VisuotactileError
from perception.geometry import ObjectModel
from perception.shapes import CLASSES, make_object
from tactile.contours import Plane, make_contour, plane_through
from tactile.explore import SequenceBatch, explore
from tactile.sampling import explore_object
from tactile.sensor import MODES, FSRSensor
from tests._fast_slow import fast_and_slow
from tests.fusion._synthetic import circle_batch

#: Probes lie on the surface within this fraction of the diagonal (plus float64 rounding of the coordinates):
#: they are float64 points of mesh edges (1e-13 mm measured); trimesh's float64 closest points are the
#: reference (Open3D's float32 distance is off by up to 5e-5 of the diagonal on sliver triangles of random
#: hulls, too coarse for this check).
ON_SURFACE = 1e-9
UNIT = 1e-9


# ------------------------------------------------------------------------------------------ meshes
def convex_hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward-wound triangles of the convex hull of ``points`` (scipy's Qhull)."""
    hull = ConvexHull(points)
    tri = hull.simplices.copy()
    a, b, c = (points[tri[:, i]] for i in range(3))
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), hull.equations[:, :3]) < 0
    tri[flip] = tri[flip][:, ::-1]
    used, inverse = np.unique(tri, return_inverse=True)
    return points[used], inverse.reshape(-1, 3)


@st.composite
def base_meshes(draw, kinds=("catalogue", "hull", "primitive"), min_hull_points=4):
    kind = draw(st.sampled_from(kinds))
    if kind == "catalogue":
        return make_object(draw(st.sampled_from(CLASSES)), draw(st.integers(0, 10**4)))
    if kind == "hull":
        # Anisotropic clouds (axes 1e-2 to 1e2 mm) give needles and slivers as well as round hulls.
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        axes = 10.0 ** np.array(draw(st.lists(st.floats(-2, 2), min_size=3, max_size=3)))
        points = rng.normal(size=(draw(st.integers(min_hull_points, 40)), 3)) * axes
        try:
            vertices, triangles = convex_hull(points)
        except QhullError:
            assume(False)
        return ObjectModel(vertices, triangles, name="hull")
    shape = draw(st.sampled_from(["sphere", "ellipsoid", "torus", "cylinder"]))
    size = st.floats(1.0, 200.0)
    if shape == "sphere":
        return primitives.sphere(draw(size), draw(st.integers(0, 3)))
    if shape == "ellipsoid":
        axes = tuple(draw(st.lists(size, min_size=3, max_size=3)))
        return primitives.ellipsoid(axes, draw(st.integers(1, 3)))
    if shape == "torus":
        major = draw(size)
        minor = major * draw(st.floats(0.05, 0.9))
        return primitives.torus(major, minor, draw(st.integers(3, 48)), draw(st.integers(3, 24)))
    return primitives.cylinder(draw(size), draw(size), draw(st.integers(3, 64)), draw(st.integers(2, 16)))


def similarity(model: ObjectModel, rotation_seed: int, scale: float, shift) -> ObjectModel:
    """``model`` rotated (a random proper rotation), scaled about the origin and shifted, mm."""
    rotation = Rotation.random(random_state=rotation_seed).as_matrix()
    vertices = scale * model.vertices @ rotation.T + np.asarray(shift)
    return ObjectModel(vertices, model.triangles, name=model.name, label=model.label)


@st.composite
def meshes(draw, **kwargs):
    """A base mesh under a random rotation, scale (0.1 to 100) and shift (within 1 m)."""
    return similarity(
        draw(base_meshes(**kwargs)),
        draw(st.integers(0, 2**32 - 1)),
        10.0 ** draw(st.floats(-1, 2)),
        draw(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3)),
    )


@st.composite
def planes_for(draw, model: ObjectModel) -> Plane:
    """A cutting plane of ``model``: through its centre and two vertices or two surface points (the
    samplers' planes), or any normal through a point of its bounding box. May raise ContourError."""
    how = draw(st.sampled_from(["vertices", "surface", "normal"]))
    n_vertices, n_triangles = model.n_vertices, model.n_triangles
    if how == "vertices":
        i, j = draw(st.integers(0, n_vertices - 1)), draw(st.integers(0, n_vertices - 1))
        return plane_through(model.center, model.vertices[i], model.vertices[j])
    if how == "surface":
        points = []
        for _ in range(2):
            t = model.vertices[model.triangles[draw(st.integers(0, n_triangles - 1))]]
            w = np.array(draw(st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3))) + 1e-9
            points.append(w / w.sum() @ t)
        return plane_through(model.center, *points)
    normal = draw(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3))
    fraction = np.array(draw(st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3)))
    lo, hi = model.bounds
    return Plane(lo + fraction * (hi - lo), normal)


# ------------------------------------------------------------------------------------------ sensors
def log_uniform(lo: float, hi: float):
    return st.floats(lo, hi).map(lambda e: 10.0**e)


@st.composite
def sensors(draw, max_taxels: int = 12) -> FSRSensor:
    """Any valid FSRSensor (within its documented ranges), on grids of up to ``max_taxels`` a side."""
    mode = draw(st.sampled_from(MODES))
    side = draw(log_uniform(-3, 4))
    standoff = draw(log_uniform(-2, 4))
    noise = log_uniform(-6, 4) if mode == "gap" else log_uniform(-30, 30)
    return FSRSensor(
        rows=draw(st.integers(1, max_taxels)),
        cols=draw(st.integers(1, max_taxels)),
        side_mm=side,
        min_side_mm=side * draw(st.floats(1e-3, 1.0)),
        mode=mode,
        range_mm=draw(log_uniform(-2, 4)),
        standoff_mm=standoff,
        indent_mm=draw(st.one_of(st.just(0.0), log_uniform(-6, 4))),
        stiffness=draw(log_uniform(-30, 30)),
        saturation=draw(log_uniform(-30, 30)),
        adc_bits=draw(st.integers(1, 32)),
        noise_std=draw(st.one_of(st.just(0.0), noise)),
        dead_taxel_rate=draw(st.one_of(st.just(0.0), st.floats(0.0, 0.999))),
        penetration_eps_mm=min(5.0, standoff * draw(st.floats(0.0, 0.99))),  # below the stand-off
        settle_mm=draw(st.one_of(st.just(0.0), log_uniform(-3, 2))),
        shrink_factor=draw(st.floats(0.05, 0.95)),
        survey_taxels=draw(st.integers(0, 16)),
    )


def ladder(sensor: FSRSensor) -> np.ndarray:
    """Every pad side the sensor may use: side * shrink**k, never below the minimum (by hand)."""
    return np.maximum(sensor.side_mm * sensor.shrink_factor ** np.arange(2000.0), sensor.min_side_mm)


# ------------------------------------------------------------------------------------------ checks
def distance_to_surface_exceeds(model: ObjectModel, points: np.ndarray, tol: float) -> np.ndarray:
    """(N,) True where a point lies further than ``tol`` (mm) from every triangle: float64 closest points of
    trimesh (a peer library), tried on the triangles whose bounding box, grown by ``tol``, holds the point."""
    triangles = model.vertices[model.triangles]
    lo, hi = triangles.min(axis=1) - tol, triangles.max(axis=1) + tol
    near = ((points[:, None] >= lo) & (points[:, None] <= hi)).all(axis=-1)
    p, f = np.nonzero(near)
    distance = np.full(len(points), np.inf)
    closest = trimesh.triangles.closest_point(triangles[f], points[p])
    np.minimum.at(distance, p, np.linalg.norm(closest - points[p], axis=1))
    return distance > tol


def check_contour(model: ObjectModel, contour, n_probes: int) -> None:
    plane = contour.plane
    for name in ("positions", "normals", "tangents"):
        array = getattr(contour, name)
        assert array.shape == (n_probes, 3) and np.isfinite(array).all(), name
    tol = ON_SURFACE * model.diagonal + 1e-12 * np.abs(model.vertices).max()  # + float64 rounding far out
    assert not distance_to_surface_exceeds(model, contour.positions, tol).any()
    extent = model.diagonal + np.abs(plane.point).max()
    assert np.abs((contour.positions - plane.point) @ plane.normal).max() <= 1e-9 * extent
    assert np.abs(np.linalg.norm(contour.normals, axis=1) - 1).max() < UNIT
    assert np.abs(np.linalg.norm(contour.tangents, axis=1) - 1).max() < UNIT
    assert np.abs(np.einsum("ij,ij->i", contour.normals, contour.tangents)).max() < UNIT


def check_sequence(sequence, sensor: FSRSensor, n_probes: int) -> None:
    frames, sides = sequence.frames, sequence.pad_sides_mm
    assert frames.shape == (n_probes, sensor.rows, sensor.cols) and frames.dtype == np.float32
    assert np.isfinite(frames).all() and frames.min() >= 0
    top = sensor.range_mm if sensor.mode == "gap" else sensor.saturation
    assert frames.max() <= np.float32(top)
    assert sides.shape == (n_probes,) and np.isfinite(sides).all()
    assert (sides >= sensor.min_side_mm).all() and (sides <= sensor.side_mm).all()
    assert np.isclose(sides[:, None], ladder(sensor)[None, :], rtol=1e-12, atol=0).any(axis=1).all()


def check_probabilities(proba: np.ndarray, n: int, n_classes: int) -> None:
    assert proba.shape == (n, n_classes) and np.isfinite(proba).all()
    assert proba.min() >= 0 and proba.max() <= 1
    np.testing.assert_allclose(proba.sum(axis=1), 1.0, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------ the whole path
@fast_and_slow(
    20,
    400,
    model=meshes(),
    sensor=sensors(),
    n_probes=st.integers(2, 30),
    seed=st.integers(0, 2**31 - 1),
    data=st.data(),
)
def _mesh_plane_sensor_to_sequence(model, sensor, n_probes, seed, data):
    try:
        contour = make_contour(model, data.draw(planes_for(model)), n_probes)
    except VisuotactileError as exc:  # a degenerate plane, or one that misses: documented, fine
        event(f"refused: {type(exc).__name__}")
        return
    check_contour(model, contour, n_probes)
    check_sequence(explore(model, contour, sensor, seed=seed), sensor, n_probes)
    event("sequence checked")


test_mesh_plane_sensor_to_sequence, test_mesh_plane_sensor_to_sequence_slow = _mesh_plane_sensor_to_sequence


@fast_and_slow(
    6,
    100,
    model=meshes(),
    n_contours=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
)
def _explored_objects_give_sequences_a_classifier_accepts(model, n_contours, seed):
    # Blind exploration (the dataset path) with the classifiers' sensor, stacked, then classified.
    sensor, probes = classifier_sensor(), PROBES
    try:
        sequences = explore_object(model, "blind", n_contours, sensor=sensor, probes=probes, seed=seed)
    except VisuotactileError as exc:
        event(f"refused: {type(exc).__name__}")
        return
    assert len(sequences) == n_contours
    for sequence in sequences:
        check_sequence(sequence, sensor, probes)
    batch = SequenceBatch.from_sequences(sequences, sensor_spec=sensor.spec())
    for name in ("frames", "normals", "positions", "tangents", "pad_sides_mm"):
        assert np.isfinite(getattr(batch, name)).all() and getattr(batch, name).dtype == np.float32
    for kind in ("knn", "svm"):
        check_probabilities(fitted(kind).predict_proba(batch), n_contours, 2)


(
    test_explored_objects_give_sequences_a_classifier_accepts,
    test_explored_objects_give_sequences_a_classifier_accepts_slow,
) = _explored_objects_give_sequences_a_classifier_accepts


# ------------------------------------------------------------------------------------- planes
FINITE_OR_NOT = st.floats(allow_nan=True, allow_infinity=True)


@fast_and_slow(
    100,
    3000,
    point=st.lists(FINITE_OR_NOT, min_size=3, max_size=3),
    normal=st.lists(FINITE_OR_NOT, min_size=3, max_size=3),
    p1=st.lists(FINITE_OR_NOT, min_size=3, max_size=3),
    p2=st.lists(FINITE_OR_NOT, min_size=3, max_size=3),
)
def _planes_from_any_numbers(point, normal, p1, p2):
    for build in (lambda: Plane(point, normal), lambda: plane_through(point, p1, p2)):
        try:
            plane = build()
        except VisuotactileError:
            continue
        assert np.isfinite(plane.point).all() and np.isfinite(plane.normal).all()
        assert abs(np.linalg.norm(plane.normal) - 1) < UNIT
        u, v = plane.basis()
        np.testing.assert_allclose(np.cross(u, v), plane.normal, atol=1e-12)


test_planes_from_any_numbers, test_planes_from_any_numbers_slow = _planes_from_any_numbers


# ------------------------------------------------------------------------------------ sensor specs
FIELDS = [f.name for f in dataclasses.fields(FSRSensor)]
ANY_VALUE = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**63),  # beyond: test_a_huge_integer_spec_value_is_a_number
    st.floats(allow_nan=True, allow_infinity=True),
    log_uniform(-40, 40),
    st.text(max_size=4),
    st.sampled_from(MODES),
    st.complex_numbers(max_magnitude=10),
    st.lists(st.integers(0, 9), max_size=2),
)


@fast_and_slow(
    150,
    5000,
    base=st.one_of(st.just({}), sensors(max_taxels=64).map(lambda s: dataclasses.asdict(s))),
    values=st.dictionaries(st.sampled_from(FIELDS), ANY_VALUE, max_size=3),
)
def _any_spec_is_valid_or_refused(base, values):
    # A valid spec (or the defaults) with up to three fields set to anything at all.
    values = {**base, **values}
    try:
        sensor = FSRSensor(**values)
    except SensorSpecError:
        event("refused")
        return
    event("accepted")
    # What the class documents for an accepted spec.
    assert 1 <= sensor.rows <= 1024 and 1 <= sensor.cols <= 1024 and 1 <= sensor.adc_bits <= 32
    assert sensor.mode in MODES and 0 <= sensor.survey_taxels <= 1024
    assert 1e-6 <= sensor.min_side_mm <= sensor.side_mm <= 1e4
    assert 0 < sensor.range_mm <= 1e4 and 0 < sensor.standoff_mm <= 1e4 and 0 <= sensor.indent_mm <= 1e4
    assert 1e-30 <= sensor.stiffness <= 1e30 and 1e-30 <= sensor.saturation <= 1e30
    assert 0 <= sensor.dead_taxel_rate < 1 and 0 < sensor.shrink_factor < 1 and sensor.noise_std >= 0
    assert 0 <= sensor.penetration_eps_mm < sensor.standoff_mm
    spec = json.loads(json.dumps(sensor.spec()))
    assert spec.pop("sensor") == "FSRSensor" and FSRSensor(**spec) == sensor


test_any_spec_is_valid_or_refused, test_any_spec_is_valid_or_refused_slow = _any_spec_is_valid_or_refused


@pytest.mark.parametrize("values", [{"rows": np.int64(16)}, {"side_mm": np.float32(20.0)}])
def test_a_spec_with_numpy_numbers_is_json(values):
    json.dumps(FSRSensor(**values).spec())


def test_a_stand_off_the_pad_cannot_see_penetration_through_is_refused():
    """Surface poking through the pad reads at most -standoff_mm: with a penetration threshold at or above it the
    adaptive pad would never settle or shrink."""
    FSRSensor(standoff_mm=0.3, penetration_eps_mm=0.2)
    for standoff in (0.2, 0.1, 1e-12):
        with pytest.raises(SensorSpecError, match=r"standoff_mm \(.*\) must exceed penetration_eps_mm \(0.2\)"):
            FSRSensor(standoff_mm=standoff, penetration_eps_mm=0.2)


def test_a_huge_integer_spec_value_is_a_number():
    assert FSRSensor(stiffness=2**64).stiffness == 2.0**64  # within [1e-30, 1e30]: valid
    with pytest.raises(SensorSpecError, match="stiffness"):
        FSRSensor(stiffness=10**400)  # beyond any float


# ------------------------------------------------------------------------------------ classifiers
PROBES = 12


def classifier_sensor() -> FSRSensor:
    return FSRSensor(rows=8, cols=8)


@cache
def training_batch() -> SequenceBatch:
    """Two classes of synthetic sequences (great circles of small and large spheres, noisy frames)."""
    radii = np.linspace(20.0, 80.0, 12)
    batch = circle_batch(radii, probes=PROBES, grid=(8, 8), seed=0, labels=(radii > 50).astype(int))
    noise = np.random.default_rng(1).normal(0, 1, batch.frames.shape)
    batch.frames = (batch.frames + noise).astype(np.float32)
    batch.sensor_spec = classifier_sensor().spec()
    return batch


@cache
def fitted(kind: str):
    return make_classifier(kind, reduce="pca", n_select=10).fit(training_batch())


#: Taxel values: ordinary readings and float32's extremes (subnormal, largest, negative, NaN, Inf).
EXTREMES = [0.0, 1e-45, 1e-30, 1e10, 1e30, 3.4e38, -3.4e38, np.nan, np.inf]
VALUES = st.one_of(st.floats(0.0, 10.0, width=32), st.sampled_from([float(np.float32(x)) for x in EXTREMES]))


@fast_and_slow(
    15,
    400,
    kind=st.sampled_from(["knn", "svm"]),
    n=st.integers(1, 4),
    fill=VALUES,
    frames=st.data(),
    normal_scale=st.sampled_from([0.0, 1.0, 1e-30, 1e30, np.inf]),
)
def _any_batch_gives_probabilities_or_a_project_error(kind, n, fill, frames, normal_scale):
    base = training_batch().subset(np.arange(n))
    with np.errstate(invalid="ignore"):  # 0 * inf: NaN normals, on purpose
        normals = (base.normals * np.float32(normal_scale)).astype(np.float32)
    batch = dataclasses.replace(
        base,
        frames=frames.draw(hnp.arrays(np.float32, base.frames.shape, elements=VALUES, fill=st.just(fill))),
        normals=normals,
    )
    try:
        proba = fitted(kind).predict_proba(batch)
    except VisuotactileError as exc:
        event(f"refused: {type(exc).__name__}")
        return
    check_probabilities(proba, n, 2)
    event("probabilities checked")


(
    test_any_batch_gives_probabilities_or_a_project_error,
    test_any_batch_gives_probabilities_or_a_project_error_slow,
) = _any_batch_gives_probabilities_or_a_project_error


# -------------------------------------------------------------------------------------- curvature
@fast_and_slow(
    6,
    120,
    model=meshes(min_hull_points=12),
    method=st.sampled_from(["discrete", "quadric"]),
)
def _curvature_is_finite(model, method):
    c = compute_curvature(model, method)
    for name in ("mean", "gaussian", "k1", "k2"):
        assert getattr(c, name).shape == (model.n_vertices,) and np.isfinite(getattr(c, name)).all(), name
    for d in (c.dir1, c.dir2):
        assert np.isfinite(d).all() and np.abs(np.linalg.norm(d, axis=1) - 1).max() < 1e-6


test_curvature_is_finite, test_curvature_is_finite_slow = _curvature_is_finite

#: pymeshlab's estimates of a rotated, scaled, shifted copy match H / s and K / s**2 within these fractions
#: of the largest |H| or |K| (measured: 4e-7 discrete, 2e-5 quadric; its arithmetic is partly float32).
COVARIANCE_TOL = {"discrete": 1e-5, "quadric": 1e-3}


@fast_and_slow(
    4,
    60,
    base=base_meshes(kinds=("catalogue", "primitive")),
    rotation_seed=st.integers(0, 2**32 - 1),
    scale=log_uniform(-2, 2),
    shift=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
    method=st.sampled_from(["discrete", "quadric"]),
)
def _curvature_follows_rotation_and_scale(base, rotation_seed, scale, shift, method):
    moved = similarity(base, rotation_seed, scale, shift)
    c0, c1 = compute_curvature(base, method), compute_curvature(moved, method)
    tol = COVARIANCE_TOL[method]
    assert np.abs(c1.mean * scale - c0.mean).max() <= tol * np.abs(c0.mean).max() + 1e-12
    assert np.abs(c1.gaussian * scale**2 - c0.gaussian).max() <= tol * np.abs(c0.gaussian).max() + 1e-12


test_curvature_follows_rotation_and_scale, test_curvature_follows_rotation_and_scale_slow = (
    _curvature_follows_rotation_and_scale
)
