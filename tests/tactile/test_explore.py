"""Exploring a contour: the tactile sequence's shapes, metadata, determinism and finiteness."""

from __future__ import annotations

import numpy as np
import pytest

from perception import primitives
from perception.errors import SensorSpecError
from perception.geometry import list_collection, load_object
from tactile import FSRSensor, explore, make_contour, plane_through
from tactile.contours import Contour


@pytest.fixture(scope="module")
def torus():
    model = primitives.torus(50.0, 20.0, 96, 48)
    model.label = "ring"
    return model


def test_sequence_carries_the_contour_and_frames(torus):
    contour = make_contour(torus, plane_through([0, 0, 0], [1, 0, 0], [0, 0.2, 1]))
    seq = explore(torus, contour, seed=3, strategy="blind")
    assert seq.frames.shape == (25, 32, 32) and seq.frames.dtype == np.float32
    assert seq.normals.shape == (25, 3) and seq.pad_sides_mm.shape == (25,)
    np.testing.assert_array_equal(seq.normals, contour.normals)
    np.testing.assert_array_equal(seq.positions, contour.positions)
    assert (seq.object_name, seq.label, seq.strategy, seq.seed, seq.plane) == (
        torus.name,
        "ring",
        "blind",
        3,
        contour.plane,
    )
    assert seq.n_probes == 25
    assert np.isfinite(seq.frames).all() and np.isfinite(seq.normals).all()
    # This plane crosses the tube twice; probes on the inner (saddle) side sit in a concave spot.
    inner = np.hypot(*seq.positions[:, :2].T) < 50.0
    assert (seq.pad_sides_mm[~inner] == 20.0).all()
    assert (seq.pad_sides_mm[inner] < 20.0).any()


def test_same_seed_same_sequence(torus):
    contour = make_contour(torus, plane_through([0, 0, 0], [1, 0, 0], [0, 0.2, 1]), n_probes=10)
    sensor = FSRSensor(noise_std=0.2, dead_taxel_rate=0.05)
    a, b = explore(torus, contour, sensor, seed=11), explore(torus, contour, sensor, seed=11)
    assert a.frames.tobytes() == b.frames.tobytes()
    assert a.frames.tobytes() != explore(torus, contour, sensor, seed=12).frames.tobytes()


def test_contour_without_probes_is_rejected(torus):
    contour = make_contour(torus, plane_through([0, 0, 0], [1, 0, 0], [0, 0.2, 1]))
    empty = Contour(contour.plane, contour.polyline, True, *(np.zeros((0, 3)),) * 3, np.zeros(0, dtype=int))
    with pytest.raises(SensorSpecError):
        explore(torus, empty)


def test_real_object_sequence_is_finite(shrec07):
    path, label = list_collection(shrec07)[70]
    model = load_object(path, label=label)
    rng = np.random.default_rng(5)
    i, j = rng.choice(model.n_vertices, 2, replace=False)
    seq = explore(
        model, make_contour(model, plane_through(model.center, model.vertices[i], model.vertices[j]))
    )
    assert seq.label == label and np.isfinite(seq.frames).all()
    assert 0.0 <= seq.frames.min() and seq.frames.max() <= FSRSensor().range_mm
