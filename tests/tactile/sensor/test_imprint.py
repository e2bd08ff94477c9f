"""The virtual FSR array against analytic imprints, the adaptive pad, determinism and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tactile.sensor as sensor_module
from perception import primitives
from perception.errors import SensorSpecError
from perception.geometry import list_collection, load_object
from tactile.contours import interpolate_normals, make_contour, plane_through
from tactile.sensor import FSRSensor


def scene_ray(model, direction):
    """A ray from the origin along ``direction`` as an Open3D tensor in ``model.scene``'s frame (the scene is built
    along the principal axes, which for a sphere are any orthonormal triple the eigen-solver returns)."""
    import open3d as o3d

    origin = model.to_scene(np.zeros(3))
    return o3d.core.Tensor(np.r_[origin, model.to_scene(direction, directions=True)].astype(np.float32)[None])


def pose_along(model, direction):
    """Probe where the ray from the origin along ``direction`` meets the surface, interpolated normal."""

    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    hit = model.scene.cast_rays(scene_ray(model, d))
    point = d * float(hit["t_hit"].numpy()[0])
    normal = interpolate_normals(model, point[None], hit["primitive_ids"].numpy().astype(np.int64))
    return point[None], normal


@pytest.fixture(scope="module")
def fine_sphere():
    return primitives.sphere(50.0, 6)


@pytest.fixture(scope="module")
def bowl():
    return primitives.hollow_hemisphere(radius_mm=30.0, thickness_mm=4.0)


# ----------------------------------------------------------------------------- analytic imprints
def test_sphere_imprint_matches_the_analytic_cap(fine_sphere):
    sensor = FSRSensor()
    position, normal = pose_along(fine_sphere, [0.2, -0.3, 0.9])
    tangent = np.cross(normal, [1.0, 0, 0])
    frames, sides = sensor.press(fine_sphere, position, normal, tangent)
    r2 = (sensor.taxel_coordinates() ** 2).sum(axis=-1)
    analytic = 50.0 - np.sqrt(50.0**2 - r2)
    error = np.abs(frames[0] - analytic).max() / np.ptp(analytic)
    assert sides[0] == 20.0
    assert error < 0.01


def test_flat_normal_is_worse_than_interpolated_normal(fine_sphere):
    sensor = FSRSensor()
    position, normal = pose_along(fine_sphere, [0.2, -0.3, 0.9])

    ray = scene_ray(fine_sphere, position[0] / np.linalg.norm(position))
    face = fine_sphere.triangle_normals[fine_sphere.scene.cast_rays(ray)["primitive_ids"].numpy()]
    analytic = 50.0 - np.sqrt(50.0**2 - (sensor.taxel_coordinates() ** 2).sum(axis=-1))
    errors = []
    for n in (normal, face):
        frames, _ = sensor.press(fine_sphere, position, n, np.cross(n, [1.0, 0, 0]))
        errors.append(np.abs(frames[0] - analytic).max() / np.ptp(analytic))
    assert errors[0] < errors[1] / 3


def test_cylinder_imprint_varies_across_the_axis_only():
    cyl = primitives.cylinder(30.0, 100.0, n_around=256, n_along=16)
    sensor = FSRSensor(rows=16, cols=16)
    # Probe on a vertex column (theta = 0), pad x along the axis, so rows run across it.
    frames, _ = sensor.press(cyl, [[30.0, 0, 0]], [[1.0, 0, 0]], [[0, 0, 1.0]])
    y = sensor.taxel_coordinates()[..., 1]
    analytic = 30.0 - np.sqrt(30.0**2 - y**2)
    assert np.abs(frames[0] - analytic).max() / np.ptp(analytic) < 0.01
    assert np.ptp(frames[0], axis=1).max() < 1e-4  # constant along the axis (columns)


def test_flat_plane_gives_an_all_zero_gap_image_and_uniform_contact():
    flat = primitives.plane(100.0, 11)
    poses = ([[0, 0, 0], [12.3, -7.0, 0]], [[0, 0, 1.0]] * 2, [[1.0, 0, 0], [0.6, 0.8, 0]])
    frames, sides = FSRSensor().press(flat, *poses)
    assert frames.dtype == np.float32 and frames.shape == (2, 32, 32)
    np.testing.assert_array_equal(frames, 0.0)
    np.testing.assert_array_equal(sides, 20.0)
    contact = FSRSensor(mode="contact", indent_mm=0.5, stiffness=2.0, saturation=4.0, adc_bits=8)
    frames, _ = contact.press(flat, *poses)
    np.testing.assert_allclose(frames, 1.0, atol=4.0 / 255)  # k * delta, within one ADC step


def test_contact_pressure_follows_the_indentation(fine_sphere):
    contact = FSRSensor(mode="contact", indent_mm=1.0, stiffness=3.0, saturation=10.0, adc_bits=16)
    position, normal = pose_along(fine_sphere, [0, 0, 1])
    frames, _ = contact.press(fine_sphere, position, normal, np.cross(normal, [1.0, 0, 0]))
    gap = 50.0 - np.sqrt(50.0**2 - (contact.taxel_coordinates() ** 2).sum(axis=-1))
    expected = 3.0 * np.maximum(0.0, 1.0 - gap)
    np.testing.assert_allclose(frames[0], expected, atol=0.02)
    saturated = FSRSensor(mode="contact", stiffness=3.0, saturation=1.0).press(
        fine_sphere, position, normal, np.cross(normal, [1.0, 0, 0])
    )[0]
    assert saturated.max() == pytest.approx(1.0)


def test_a_miss_reads_the_range_without_nan(fine_sphere):
    sensor = FSRSensor(range_mm=7.0)
    frames, sides = sensor.press(fine_sphere, [[0, 0, 200.0]], [[0, 0, 1.0]], [[1.0, 0, 0]])
    np.testing.assert_array_equal(frames, 7.0)
    assert sides[0] == 20.0


def test_columns_follow_the_tangent():
    # The pad tilted about its y axis: the gap changes along columns (pad x) only.
    flat = primitives.plane(100.0, 11)
    tilt = np.radians(5.0)
    normal = np.array([[np.sin(tilt), 0, np.cos(tilt)]])
    sensor = FSRSensor(rows=8, cols=8)
    x = sensor.taxel_coordinates()[..., 0]
    gaps = sensor.measure_gaps(
        flat, np.zeros((1, 3)), normal, np.array([[np.cos(tilt), 0, -np.sin(tilt)]]), np.array([20.0])
    )
    np.testing.assert_allclose(gaps[0], -x * np.tan(tilt), atol=1e-5)
    frames, _ = sensor.press(flat, np.zeros((1, 3)), normal, [[1.0, 0, 0]], adaptive=False)
    np.testing.assert_allclose(frames[0], np.clip(-x * np.tan(tilt), 0, None), atol=1e-5)


# ------------------------------------------------------------------------------- adaptive pad
def test_pad_shrinks_inside_a_bowl(bowl):
    sensor = FSRSensor()
    bottom = np.array([[0, 0, -26.0]])
    raw = sensor.measure_gaps(
        bowl, bottom, np.array([[0, 0, 1.0]]), np.array([[1.0, 0, 0]]), np.array([20.0])
    )
    expected_sag = 26.0 - np.sqrt(26.0**2 - 2 * 10.0**2 * (31 / 32) ** 2)  # corner taxel of the flat pad
    assert raw.min() == pytest.approx(-expected_sag, abs=0.05)
    _, sides = sensor.press(bowl, bottom, [[0, 0, 1.0]], [[1.0, 0, 0]])
    assert sides[0] < 20.0
    np.testing.assert_array_equal(
        FSRSensor().press(bowl, bottom, [[0, 0, 1.0]], [[1.0, 0, 0]], adaptive=False)[1], 20.0
    )


def stepwise_sides(sensor, model, positions, normals, tangents):
    """Reference rule: walk the side ladder down one step at a time; the first side that does not
    penetrate (or min_side_mm)."""
    ladder = np.unique(sensor.side_mm * sensor.shrink_factor ** np.arange(40.0))
    ladder = np.unique(np.maximum(ladder, sensor.min_side_mm))[::-1]
    result = np.full(len(positions), sensor.min_side_mm)
    todo = np.arange(len(positions))
    for side in ladder:
        gaps = sensor.measure_gaps(
            model, positions[todo], normals[todo], tangents[todo], np.full(len(todo), side)
        )
        fits = gaps.min(axis=(1, 2)) >= -sensor.penetration_eps_mm
        result[todo[fits]] = side
        todo = todo[~fits]
    return result


@pytest.mark.parametrize("survey", [0, 8])
def test_adaptive_sides_match_the_stepwise_rule_in_a_bowl(bowl, survey):
    sensor = FSRSensor(min_side_mm=2.0, penetration_eps_mm=0.05, survey_taxels=survey)
    angles = np.radians(np.linspace(0, 60, 7))
    inner = 26.0
    positions = np.stack([inner * np.sin(angles), np.zeros_like(angles), -inner * np.cos(angles)], axis=1)
    normals = -positions / inner  # the surface normal inside the bowl points to its centre
    tangents = np.tile([0, 1.0, 0], (len(angles), 1))
    _, sides = sensor.press(bowl, positions, normals, tangents)
    reference = stepwise_sides(sensor, bowl, positions, normals, tangents)
    np.testing.assert_allclose(sides, reference)
    assert (sides < 20.0).all()
    # Final pads either fit or are at the smallest side.
    gaps = sensor.measure_gaps(bowl, positions, normals, tangents, sides)
    assert ((gaps.min(axis=(1, 2)) >= -sensor.penetration_eps_mm) | (sides == sensor.min_side_mm)).all()


@pytest.mark.parametrize("survey", [0, 8])
def test_adaptive_frames_equal_a_fresh_cast_at_the_chosen_sides(bowl, survey):
    # The full cast after the survey reuses the survey's readings: they must be the very bytes a
    # fresh cast of the whole pad at the chosen side gives.
    sensor = FSRSensor(min_side_mm=1.0, penetration_eps_mm=0.5, survey_taxels=survey)
    angles = np.radians(np.linspace(0, 60, 5))
    inside = np.stack([26.0 * np.sin(angles), np.zeros_like(angles), -26.0 * np.cos(angles)], axis=1)
    positions = np.concatenate([inside, [[0, 0, -30.0], [0, 30.0, 0]]])
    normals = np.concatenate([-inside / 26.0, [[0, 0, -1.0], [0, 1.0, 0]]])
    tangents = np.tile([1.0, 0, 0], (len(positions), 1))
    frames, sides = sensor.press(bowl, positions, normals, tangents)
    assert (sides[:5] < 20.0).all() and (sides[5:] == 20.0).all()
    fresh = np.clip(sensor.measure_gaps(bowl, positions, normals, tangents, sides), 0.0, sensor.range_mm)
    assert frames.tobytes() == fresh.tobytes()


def test_convex_pads_do_not_shrink(fine_sphere):
    contour = make_contour(fine_sphere, plane_through([0, 0, 0], [1, 0.2, 0], [0, 0.3, 1]))
    _, sides = FSRSensor().press(fine_sphere, contour.positions, contour.normals, contour.tangents)
    np.testing.assert_array_equal(sides, 20.0)


def test_surface_above_the_standoff_reads_as_penetration(bowl):
    # With a 1 mm stand-off the corner rays of a 20 mm pad start inside the bowl wall.
    sensor = FSRSensor(standoff_mm=1.0)
    gaps = sensor.measure_gaps(
        bowl, np.array([[0, 0, -26.0]]), np.array([[0, 0, 1.0]]), np.array([[1.0, 0, 0]]), np.array([20.0])
    )
    assert gaps.min() == pytest.approx(-1.0)
    assert (gaps[0, 0, 0], gaps[0, 15, 15]) == (pytest.approx(-1.0), pytest.approx(0.0, abs=0.05))


@settings(max_examples=15, deadline=None)
@given(
    side=st.floats(1.0, 40.0),
    factor=st.floats(0.05, 0.95),
    min_fraction=st.floats(0.01, 1.0),
    eps=st.floats(0.0, 0.5),
    survey=st.integers(0, 20),
)
def test_adaptive_pad_terminates_on_the_ladder(bowl, side, factor, min_fraction, eps, survey):
    sensor = FSRSensor(
        rows=8,
        cols=8,
        side_mm=side,
        min_side_mm=side * min_fraction,
        shrink_factor=factor,
        penetration_eps_mm=eps,
        survey_taxels=survey,
    )
    positions = np.array([[0, 0, -26.0], [0, 0, -30.0], [26.0, 0, 0.0]])
    normals = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]])
    frames, sides = sensor.press(bowl, positions, normals, [[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    assert np.isfinite(frames).all()
    assert ((sides <= side) & (sides >= sensor.min_side_mm - 1e-12)).all()
    k = np.log(sides / side) / np.log(factor)
    on_ladder = np.isclose(k, np.round(k)) | np.isclose(sides, sensor.min_side_mm)
    assert on_ladder.all()


# --------------------------------------------------------------------- determinism and batching
def test_same_seed_same_bytes_with_noise_and_dead_taxels(fine_sphere):
    sensor = FSRSensor(mode="contact", noise_std=0.05, dead_taxel_rate=0.1)
    contour = make_contour(fine_sphere, plane_through([0, 0, 0], [1, 0, 0], [0, 1, 1]), n_probes=5)
    poses = (contour.positions, contour.normals, contour.tangents)
    a, _ = sensor.press(fine_sphere, *poses, seed=7)
    b, _ = sensor.press(fine_sphere, *poses, seed=7)
    c, _ = sensor.press(fine_sphere, *poses, seed=np.random.default_rng(7))
    d, _ = sensor.press(fine_sphere, *poses, seed=8)
    assert a.tobytes() == b.tobytes() == c.tobytes()
    assert a.tobytes() != d.tobytes()


def test_dead_taxels_are_the_same_in_every_frame():
    flat = primitives.plane(100.0, 11)
    sensor = FSRSensor(dead_taxel_rate=0.3)
    frames, _ = sensor.press(flat, [[0, 0, 0], [5.0, 5.0, 0]], [[0, 0, 1.0]] * 2, [[1.0, 0, 0]] * 2, seed=1)
    dead = frames[0] == sensor.range_mm
    np.testing.assert_array_equal(frames[1] == sensor.range_mm, dead)
    assert 0.2 < dead.mean() < 0.4


def test_batches_give_the_same_frames(fine_sphere, monkeypatch):
    contour = make_contour(fine_sphere, plane_through([0, 0, 0], [1, 0, 0], [0, 1, 1]), n_probes=7)
    poses = (contour.positions, contour.normals, contour.tangents)
    one, _ = FSRSensor().press(fine_sphere, *poses)
    monkeypatch.setattr(sensor_module, "MAX_RAYS_PER_CAST", 2 * 1024)
    split, _ = FSRSensor().press(fine_sphere, *poses)
    np.testing.assert_array_equal(one, split)


def test_real_meshes_give_finite_frames(shrec07):
    model = load_object(list_collection(shrec07)[40][0])
    rng = np.random.default_rng(2)
    sensor = FSRSensor()
    for _ in range(3):
        i, j = rng.choice(model.n_vertices, 2, replace=False)
        contour = make_contour(model, plane_through(model.center, model.vertices[i], model.vertices[j]))
        frames, sides = sensor.press(model, contour.positions, contour.normals, contour.tangents)
        assert np.isfinite(frames).all() and frames.min() >= 0 and frames.max() <= sensor.range_mm
        assert ((sides >= sensor.min_side_mm) & (sides <= sensor.side_mm)).all()


# ---------------------------------------------------------------------------------- spec, bad input
def test_spec_is_json_and_rebuilds_the_sensor():
    sensor = FSRSensor(rows=16, mode="contact", noise_std=0.1)
    spec = json.loads(json.dumps(sensor.spec()))
    assert spec.pop("sensor") == "FSRSensor"
    assert FSRSensor(**spec) == sensor


@pytest.mark.parametrize(
    "field, value",
    [
        ("rows", 0),
        ("cols", -4),
        ("rows", 2.5),
        ("rows", True),
        ("side_mm", 0.0),
        ("side_mm", -20.0),
        ("side_mm", float("nan")),
        ("min_side_mm", 0.0),
        ("min_side_mm", 30.0),
        ("range_mm", 0.0),
        ("standoff_mm", -1.0),
        ("stiffness", 0.0),
        ("saturation", -1.0),
        ("indent_mm", -0.1),
        ("noise_std", -1.0),
        ("dead_taxel_rate", 1.0),
        ("shrink_factor", 1.0),
        ("shrink_factor", 0.0),
        ("mode", "force"),
        ("adc_bits", 0),
        ("survey_taxels", -1),
        ("penetration_eps_mm", float("inf")),
        ("settle_mm", -0.5),
        ("side_mm", "20"),
    ],
)
def test_bad_specs_are_rejected(field, value):
    with pytest.raises(SensorSpecError, match=field):
        FSRSensor(**{field: value})


@pytest.mark.parametrize(
    "positions, normals, tangents",
    [
        (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))),
        ([], [], []),
        ([[0, 0, 0]], [[0, 0, 1.0]] * 2, [[1.0, 0, 0]]),
        ([[0, 0, np.nan]], [[0, 0, 1.0]], [[1.0, 0, 0]]),
        ([[0, 0, 0]], [[0, 0, 0.0]], [[1.0, 0, 0]]),
        ([[0, 0]], [[0, 0, 1.0]], [[1.0, 0, 0]]),
        ([["a", 0, 0]], [[0, 0, 1.0]], [[1.0, 0, 0]]),
    ],
)
def test_bad_probes_are_rejected(fine_sphere, positions, normals, tangents):
    with pytest.raises(SensorSpecError, match=fine_sphere.name):
        FSRSensor().press(fine_sphere, positions, normals, tangents)


def test_tangent_parallel_to_the_normal_still_gives_a_pad(fine_sphere):
    position, normal = pose_along(fine_sphere, [0, 0, 1])
    frames, _ = FSRSensor().press(fine_sphere, position, normal, normal)
    assert np.isfinite(frames).all() and frames.max() > 1.0
