"""Robustness on the tactile side: extreme sensor settings, bad seeds and counts, degenerate planes, a flat
plate, an inward-wound object, and figures that leave the user's matplotlib backend alone."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from perception import primitives
from perception.errors import ContourError, InvalidArgumentError, SensorSpecError
from perception.geometry import ObjectModel, load_object
from tactile.contours import Plane, make_contour, plane_through
from tactile.sampling import explore_object, sample_planes
from tactile.sensor import FSRSensor

SMALL = {"rows": 8, "cols": 8}


@pytest.fixture(scope="module")
def ball() -> ObjectModel:
    return primitives.sphere(43.0, 4)


@pytest.mark.parametrize(
    "settings",
    [
        {"mode": "contact", "saturation": 1e-306},
        {"range_mm": 1e39},
        {"standoff_mm": 1e39},
        {"side_mm": 1e300, "min_side_mm": 1.0},
        {"mode": "contact", "stiffness": 1e300},
        {"noise_std": 1e30},
    ],
)
def test_extreme_sensor_settings_are_refused(settings):
    with pytest.raises(SensorSpecError, match=next(iter(settings.keys() - {"mode", "min_side_mm"}))):
        FSRSensor(**settings)


def test_the_most_extreme_accepted_settings_read_finite(ball):
    contour = make_contour(ball, plane_through(ball.center, [1, 0, 0], [0, 1, 0]), 5)
    poses = (contour.positions, contour.normals, contour.tangents)
    contact = FSRSensor(mode="contact", saturation=1e-30, stiffness=1e30, **SMALL)
    frames, _ = contact.press(ball, *poses)
    assert np.isfinite(frames).all()
    # Every taxel that touches saturates at 1e-30 (stiffness 1e30 x indentation), exactly representable.
    assert frames.max() == np.float32(1e-30) and frames.min() == 0.0
    far = FSRSensor(range_mm=1e4, standoff_mm=1e4, **SMALL)
    frames, _ = far.press(ball, *poses)
    assert np.isfinite(frames).all() and frames.max() <= 1e4


def test_negative_and_fractional_arguments_raise_project_errors(ball):
    contour = make_contour(ball, plane_through(ball.center, [1, 0, 0], [0, 1, 0]), 4)
    with pytest.raises(SensorSpecError, match="seed"):
        FSRSensor(**SMALL).press(ball, contour.positions, contour.normals, contour.tangents, seed=-1)
    with pytest.raises(InvalidArgumentError, match="seed"):
        explore_object(ball, "blind", 1, seed=-1)
    with pytest.raises(InvalidArgumentError, match="n_contours"):
        explore_object(ball, "blind", 2.5)
    with pytest.raises(InvalidArgumentError, match="probes"):
        explore_object(ball, "blind", 1, probes=3.5)
    with pytest.raises(InvalidArgumentError, match="n must"):
        sample_planes(ball, "blind", 2.5)
    with pytest.raises(InvalidArgumentError, match="seed"):
        sample_planes(ball, "blind", 1, seed=1.5)
    assert len(sample_planes(ball, "blind", 2.0)) == 2  # an integral float is a count


def test_planes_with_extreme_numbers():
    with pytest.raises(ContourError, match="further than"):
        Plane([1e308, 0.0, 0.0], [0.0, 0.0, 1.0])
    plane = Plane([0.0, 0.0, 0.0], [1e308, 1e308, 0.0])
    np.testing.assert_allclose(plane.normal, [2**-0.5, 2**-0.5, 0.0])
    u, v = plane.basis()
    assert np.isfinite(u).all() and np.isfinite(v).all()
    np.testing.assert_allclose(np.cross(u, v), plane.normal, atol=1e-15)
    np.testing.assert_allclose(Plane([0, 0, 0], [0, 3e-300, 0]).normal, [0, 1, 0])
    # Points at 1e308 from the centre still span a plane (their difference would overflow).
    np.testing.assert_allclose(plane_through([0, 0, 0], [1e308, 1.0, 0.0], [-1e308, 1e308, 0.0]).normal, [0, 0, 1])


def test_flat_plate_is_refused_with_the_reason():
    plate = primitives.plane(100.0, 11)
    for strategy in ("blind", "mesh"):
        with pytest.raises(ContourError, match="flat"):
            explore_object(plate, strategy, 1)
    with pytest.raises(ContourError, match="contains"):
        make_contour(plate, Plane(plate.center, [0.0, 0.0, 1.0]), 5)
    # A cut across the plate is proper: an open chain from edge to edge, 100 mm long.
    across = make_contour(plate, Plane(plate.center, [1.0, 0.0, 0.0]), 5)
    assert not across.closed and across.length_mm == pytest.approx(100.0)


def test_inward_wound_sphere_explores_like_the_analytic_sphere(tmp_path):
    s = primitives.sphere(43.0, 5)
    path = tmp_path / "inward.off"
    lines = ["OFF", f"{s.n_vertices} {s.n_triangles} 0"]
    lines += [" ".join(map(repr, v.tolist())) for v in s.vertices]
    lines += ["3 " + " ".join(map(str, t)) for t in s.triangles[:, ::-1]]
    path.write_text("\n".join(lines) + "\n")
    model = load_object(path, size_mm=None)
    sensor = FSRSensor(**SMALL)
    (sequence,) = explore_object(model, "blind", 1, sensor=sensor, probes=6, seed=0)
    assert (np.einsum("ij,ij->i", sequence.normals, sequence.positions) > 0.999 * 43.0).all()
    np.testing.assert_array_equal(sequence.pad_sides_mm, 20.0)  # a convex ball never shrinks the pad
    # Analytic imprint: a taxel at distance rho from the pad centre sees the sphere R - sqrt(R^2 - rho^2) away.
    xy = sensor.taxel_coordinates()
    rho2 = (xy**2).sum(axis=-1)
    expected = 43.0 - np.sqrt(43.0**2 - rho2)
    assert np.abs(sequence.frames - expected).max() < 0.05  # tessellation: sagitta of 1.3 mm edges


def test_figures_leave_the_matplotlib_backend_alone(tmp_path):
    script = f"""
import matplotlib
matplotlib.use("svg")
import tactile.figures
from perception import primitives
from perception.saliency import plot_channels, plot_saliency, saliency
from tactile.sampling import explore_object
from tactile.contours import make_contour, plane_through
from tactile.sensor import FSRSensor
m = primitives.sphere(40.0, 2)
assert matplotlib.get_backend() == "svg", matplotlib.get_backend()
c = make_contour(m, plane_through(m.center, [1, 0, 0], [0, 1, 0]), 4)
from tactile.explore import explore
tactile.figures.plot_sequence(m, c, explore(m, c, FSRSensor(rows=4, cols=4)), r"{tmp_path / 'seq.png'}")
plot_saliency(saliency(m, "iss"), r"{tmp_path / 'sal.png'}", n_points=2, size_px=32)
plot_channels(m, r"{tmp_path / 'ch.png'}", n_rows=1, n_views=2, size_px=32)
assert matplotlib.get_backend() == "svg", matplotlib.get_backend()
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("ok")
    for name in ("seq.png", "sal.png", "ch.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
