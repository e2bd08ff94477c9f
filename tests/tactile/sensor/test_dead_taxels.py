"""Dead taxels: found only where a taxel reads nothing all along a sequence among live neighbours; filled in
from them (exact on a plane, close to the clean press on a sphere)."""

from __future__ import annotations

import numpy as np
import pytest

from perception.errors import SensorSpecError
from perception.primitives import sphere
from tactile.dead_taxels import _neighbour_sum, find_dead_taxels, repair_dead_taxels
from tactile.sensor import FSRSensor

SENSOR = FSRSensor(rows=8, cols=8)


def ramp_sequence(probes: int = 5) -> np.ndarray:
    """(P, 8, 8) gaps that vary linearly across the pad and between frames, all inside the range."""
    r, c = np.mgrid[0:8, 0:8]
    return np.stack([0.5 + 0.3 * r + 0.2 * c + 0.1 * p for p in range(probes)]).astype(np.float32)


def test_isolated_dead_taxels_are_found_and_filled_exactly_on_a_linear_surface():
    clean = ramp_sequence()
    broken = clean.copy()
    dead = [(0, 0), (3, 4), (7, 2), (5, 7)]  # a corner, the middle, two edges
    for r, c in dead:
        broken[:, r, c] = SENSOR.range_mm
    mask = find_dead_taxels(broken, SENSOR)
    assert {tuple(x) for x in np.argwhere(mask)} == set(dead)
    repaired = repair_dead_taxels(broken, SENSOR)
    assert repaired.dtype == np.float32
    # Inside: the mean of 8 neighbours of a linear function is its centre value. At the border the mean of
    # the in-bounds neighbours is not symmetric: compute it by hand for the corner (0, 0): neighbours (0, 1),
    # (1, 0), (1, 1) -> mean of 0.2 c + 0.3 r over them = (0.2 + 0.3 + 0.5) / 3.
    np.testing.assert_allclose(repaired[:, 3, 4], clean[:, 3, 4], atol=1e-6)
    np.testing.assert_allclose(repaired[:, 0, 0], 0.5 + 0.1 * np.arange(5) + 1.0 / 3, atol=1e-6)
    untouched = np.ones((8, 8), bool)
    untouched[tuple(np.array(dead).T)] = False
    np.testing.assert_array_equal(repaired[:, untouched], clean[:, untouched])


def test_a_block_that_reads_nothing_and_a_taxel_that_sometimes_does_are_left_alone():
    frames = ramp_sequence()
    frames[:, :, 5:] = SENSOR.range_mm  # the pad hangs over an edge along the whole contour: 3 columns
    frames[2, 1, 1] = SENSOR.range_mm  # one frame only: a real miss, not a dead taxel
    assert not find_dead_taxels(frames, SENSOR).any()
    np.testing.assert_array_equal(repair_dead_taxels(frames, SENSOR), frames)


def test_contact_mode_dead_taxels_read_zero_and_batches_are_per_sequence():
    sensor = FSRSensor(rows=8, cols=8, mode="contact")
    batch = np.stack([ramp_sequence(), ramp_sequence() + 1.0])  # (S=2, P, R, C)
    batch[0, :, 2, 2] = 0.0  # dead in the first sequence only
    mask = find_dead_taxels(batch, sensor)
    assert mask.shape == (2, 8, 8) and mask[0, 2, 2] and mask.sum() == 1
    repaired = repair_dead_taxels(batch, sensor)
    np.testing.assert_allclose(repaired[0, :, 2, 2], ramp_sequence()[:, 2, 2], atol=1e-6)
    np.testing.assert_array_equal(repaired[1], batch[1])


def test_dead_taxels_of_the_sensor_are_repaired_close_to_the_clean_press():
    # A sphere of radius R = 40 mm pressed by a 32 x 32 pad (pitch h = 0.625 mm) with 5 % dead taxels. The
    # 8-neighbour mean of a smooth gap f misses the centre by (3/8) h^2 (f_xx + f_yy); for the sphere's gap
    # R - sqrt(R^2 - r^2) that is largest at the pad corners (r^2 = 200 mm^2), plus the facets' sagitta
    # e^2 / 8R (icosphere edge e ~ 1.05 R / 64) on each side. Next to another dead taxel or at the border the
    # mean is one-sided, off by up to the slope (at most 14.1 / R at the corners) times h.
    model = sphere(40.0, subdivisions=6)
    sensor, clean_sensor = FSRSensor(dead_taxel_rate=0.05), FSRSensor()
    theta = np.linspace(0.3, 2.8, 12)
    positions = 40.0 * np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)
    normals = positions / 40.0
    tangents = np.stack([np.cos(theta), np.zeros_like(theta), -np.sin(theta)], axis=1)
    noisy, _ = sensor.press(model, positions, normals, tangents, seed=4)
    clean, _ = clean_sensor.press(model, positions, normals, tangents)
    dead = find_dead_taxels(noisy, sensor)
    assert 0.02 < dead.mean() < 0.08  # about 5 % of the taxels, found without the map
    assert np.abs(noisy - clean).max() > 5.0  # a dead taxel reads the 10 mm range on contact
    repaired = repair_dead_taxels(noisy, sensor)
    error = np.abs(repaired - clean)
    assert error.max() < 14.1 / 40.0 * 0.625
    inner = np.zeros((32, 32), bool)
    inner[1:-1, 1:-1] = True
    lone = dead & inner & (_neighbour_sum(dead.astype(int)) == 0)
    f_xx = (40.0**2 - 100.0) / (40.0**2 - 200.0) ** 1.5  # = f_yy at a corner
    sagitta = (1.05 * 40.0 / 64) ** 2 / (8 * 40.0)
    assert lone.any() and error[:, lone].max() < 3 / 8 * 0.625**2 * 2 * f_xx + 2 * sagitta


def test_bad_frames_are_refused():
    with pytest.raises(SensorSpecError, match="shape"):
        repair_dead_taxels(np.zeros((5, 4, 4)), SENSOR)
    with pytest.raises(SensorSpecError, match="NaN"):
        find_dead_taxels(np.full((2, 8, 8), np.nan), SENSOR)
