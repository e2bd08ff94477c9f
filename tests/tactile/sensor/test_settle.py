"""The pad settles on rough surfaces (tilted normals, ripples) but still shrinks into real concavities."""

from __future__ import annotations

import numpy as np
import pytest

from perception import primitives
from perception.errors import SensorSpecError
from perception.geometry import ObjectModel
from tactile.sensor import FSRSensor

RIPPLE_MM, WAVELENGTH_MM = 0.3, 4.0


def heightfield(height, side_mm: float = 40.0, nx: int = 401, ny: int = 41) -> ObjectModel:
    """Open grid mesh z = height(x) over a side_mm square centred at the origin, normal +z."""
    x, y = np.linspace(-side_mm / 2, side_mm / 2, nx), np.linspace(-side_mm / 2, side_mm / 2, ny)
    xx, yy = np.meshgrid(x, y, indexing="ij")
    vertices = np.stack([xx.ravel(), yy.ravel(), height(xx.ravel())], axis=1)
    a = (np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]).ravel()
    triangles = np.concatenate([np.stack([a, a + ny, a + ny + 1], 1), np.stack([a, a + ny + 1, a + 1], 1)])
    return ObjectModel(vertices, triangles, name="heightfield")


def ripple(x):
    return RIPPLE_MM * np.sin(2 * np.pi * x / WAVELENGTH_MM)


@pytest.fixture(scope="module")
def flat():
    return heightfield(np.zeros_like, nx=41)


@pytest.fixture(scope="module")
def rippled():
    return heightfield(ripple)


def test_a_tilted_pad_settles_flat_on_a_plane(flat):
    tilt = np.radians(3.0)
    normal = [[np.sin(tilt), 0.0, np.cos(tilt)]]
    pose = ([[0.0, 0.0, 0.0]], normal, [[1.0, 0.0, 0.0]])
    # Tilted 3 degrees, the pad's edge taxels lie 10 mm * 31/32 * tan(3 deg) = 0.51 mm below the plane.
    rigid = FSRSensor(settle_mm=0.0)
    raw = rigid.measure_gaps(flat, *pose, 20.0)
    assert raw.min() == pytest.approx(-10 * 31 / 32 * np.tan(tilt), abs=0.02)
    assert rigid.press(flat, *pose)[1][0] < 20.0
    frames, sides = FSRSensor().press(flat, *pose)
    assert sides[0] == 20.0
    np.testing.assert_allclose(frames[0], 0.0, atol=1e-4)  # level on the plane: a flat plane reads zero


def test_a_pad_settles_on_the_least_squares_plane_of_a_ripple_and_rests_on_its_crest(rippled):
    pose = ([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    sensor = FSRSensor(survey_taxels=0)  # one full-resolution cast: the fit sees every taxel
    frames, sides = sensor.press(rippled, *pose)
    assert sides[0] == 20.0
    # By hand: the least-squares line through the ripple under the 32 taxel columns (the ripple is odd
    # about the probe, so the fit tilts by a = cov(x, ripple) / var(x)), raised to the highest residual.
    x = sensor.taxel_coordinates()[0, :, 0]
    (a, _), *_ = np.linalg.lstsq(np.stack([x, np.ones_like(x)], 1), ripple(x), rcond=None)
    lift = np.max(ripple(x) - a * x)
    expected = lift + a * x - ripple(x)  # gap under each column of the tilted, raised pad (tilt < 0.4 deg)
    np.testing.assert_allclose(frames[0], np.broadcast_to(expected, (32, 32)), atol=3e-3)
    # With the survey the pad settles on the 8 x 8 survey first, then on the full grid if needed.
    frames, sides = FSRSensor().press(rippled, *pose)
    assert sides[0] == 20.0 and frames.min() == 0.0 and frames.max() < 2 * RIPPLE_MM + 0.2
    # A pad that may not rise that far, or never settles, shrinks instead.
    for survey in (0, 8):
        for other in (FSRSensor(settle_mm=0.2, survey_taxels=survey), FSRSensor(settle_mm=0.0, survey_taxels=survey)):
            assert other.press(rippled, *pose)[1][0] < 20.0


def test_a_concavity_deeper_than_the_settling_still_shrinks_the_pad():
    # The bottom of a bowl of inner radius r = 26 mm sags r - sqrt(r**2 - 2 (s/2)**2) under the corners of a
    # pad of side s: 3.9 mm at 20 mm, far beyond the 1 mm of settling, so the pad shrinks as a rigid one does,
    # down to the first ladder side where the sag is within the 0.2 mm tolerance (4.19 mm: 0.17 mm).
    bowl = primitives.hollow_hemisphere(radius_mm=30.0, thickness_mm=4.0)
    pose = ([[0, 0, -26.0]], [[0, 0, 1.0]], [[1.0, 0, 0]])
    rigid_frames, rigid_sides = FSRSensor(settle_mm=0.0, min_side_mm=2.0).press(bowl, *pose)
    frames, sides = FSRSensor(min_side_mm=2.0).press(bowl, *pose)
    assert sides[0] == rigid_sides[0] == pytest.approx(20 * 0.8**7)
    assert frames.tobytes() == rigid_frames.tobytes()
    # At the smallest side (5 mm: 0.24 mm sag) a pad that still pokes through rests on the rim instead:
    # raised by the sag, its reading is the rigid one plus the lift (0 where the rigid pad penetrated).
    rigid_frames, _ = FSRSensor(settle_mm=0.0).press(bowl, *pose)
    frames, sides = FSRSensor().press(bowl, *pose)
    sag = 26.0 - np.sqrt(26.0**2 - 2 * (2.5 * 31 / 32) ** 2)
    assert sides[0] == 5.0
    assert frames.max() - rigid_frames.max() == pytest.approx(sag, abs=0.02)
    assert frames.min() == pytest.approx(0.0, abs=1e-3)


def test_convex_surfaces_read_the_same_bytes_with_or_without_settling():
    sphere = primitives.sphere(50.0, 6)
    directions = np.array([[0.2, -0.3, 0.9], [1.0, 0.1, 0.0], [-0.4, 0.5, -0.6]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    positions, normals = 49.99 * directions, directions
    tangents = np.cross(normals, [0.0, 0.0, 1.0])
    rigid = FSRSensor(settle_mm=0.0).press(sphere, positions, normals, tangents)
    settling = FSRSensor().press(sphere, positions, normals, tangents)
    assert rigid[0].tobytes() == settling[0].tobytes()
    np.testing.assert_array_equal(settling[1], 20.0)


def test_specs_from_before_settling_describe_a_rigid_pad():
    spec = FSRSensor().spec()
    assert FSRSensor.from_spec(spec) == FSRSensor()
    del spec["settle_mm"]  # as written by versions without settling
    assert FSRSensor.from_spec(spec).settle_mm == 0.0
    with pytest.raises(SensorSpecError, match="unknown fields"):
        FSRSensor.from_spec({**spec, "stickiness": 1.0})
