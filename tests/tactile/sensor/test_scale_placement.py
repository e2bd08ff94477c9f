"""Scale and placement: the same object at 1e-3, 1 and 1e4 of its units, and 1e6 mm from the origin,
gives the same tactile sequences once normalised, and float32 ray casting never loses contact because of where
the object sits.

Two ways to normalise: ``load_object`` (re-centred, scaled to a 150 mm diagonal; the supported path), and
a raw ``ObjectModel`` at scale s pressed by a sensor whose lengths are all s times a base sensor's (readings
/ s and pad sides / s compared; in contact mode stiffness / s gives the same pressures). FSRSensor caps
lengths at 1e4 mm, so the base is the default sensor scaled by 1/20 (a 1 mm pad) on the object at 7.5 mm:
the default geometry, whose 1e4-times copy (a 1e4 mm pad on a 75 m object) is still a valid spec. The
translated copy is compared raw (no re-centring): the scene is cast around the object's centre, so it keeps
contact and reads the same frames.
"""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import open3d as o3d
import pytest
from hypothesis import event
from hypothesis import strategies as st

from perception.errors import ContourError, SensorSpecError
from perception.geometry import ObjectModel, load_object
from perception.shapes import CLASSES, make_object
from tactile.contours import make_contour, plane_through
from tactile.explore import explore
from tactile.sensor import FSRSensor
from tests._fast_slow import fast_and_slow

LENGTHS = ("side_mm", "min_side_mm", "range_mm", "standoff_mm", "indent_mm", "penetration_eps_mm", "settle_mm")
SCALES = (1e-3, 1.0, 1e4)
OFFSET_MM = 1e6
#: Readings of scaled copies agree within this fraction of the object's diagonal. float32 ray casting
#: resolves 6e-8 of the coordinates; oblique hits on facets magnify that: measured 2e-6 of the diagonal at
#: worst on the catalogue (1.5e-5 mm on a 7.5 mm box), so 1e-5 leaves a factor of 5.
SCALE_TOL = 1e-5
#: After load_object the copies differ by the float64 rounding of the input, ``input_rounding``: 1.2e-7 mm
#: at worst (an object 0.15 units wide at 1e6 units, scaled up 1000 times). That moves probes up to 32 times
#: as much (faces nearly parallel to the cutting plane), normals 5 times (per mm), and flips the float32
#: rounding of some vertices (7.6e-6 mm at 75 mm): readings agree within LOAD_TOL_MM plus 1000 times it, times
#: 1 / cos of the incidence where a ray meets the surface obliquely (measured: 0.77 of that bound at worst, on the
#: bowl at 1e4 units 1e6 away; the rims the bound without the cosine missed by up to 3 times).
LOAD_TOL_MM = 1e-4
#: An odd taxel grid has a taxel at the pad centre, exactly over the probe on the surface: its gap is 0 up
#: to float32 rounding (measured: 3e-6 mm near the origin, one ulp of the coordinates, 0.06 mm, at 1e6 mm).
CENTRE = 7
ODD = {"rows": 15, "cols": 15}


def scaled_sensor(base: FSRSensor, s: float) -> FSRSensor:
    """``base`` with every length times ``s`` and the stiffness divided by ``s`` (same pressures)."""
    lengths = {k: getattr(base, k) * s for k in LENGTHS}
    return dataclasses.replace(base, stiffness=base.stiffness / s, **lengths)


def base_sensor(mode: str = "gap") -> FSRSensor:
    default = FSRSensor(mode=mode, saturation=2.0, adc_bits=16, **ODD)
    return scaled_sensor(default, 1 / 20)


@cache
def catalogue(cls: str, seed: int, size_mm: float = 150.0) -> ObjectModel:
    return make_object(cls, seed, size_mm=size_mm)


def plane_of(model: ObjectModel, i: int, j: int):
    """The plane through the centre and vertices i and j (indices taken modulo the vertex count)."""
    n = model.n_vertices
    return plane_through(model.center, model.vertices[i % n], model.vertices[j % n])


# ------------------------------------------------------------------------------- through load_object
@cache
def loaded(cls: str, scale: float, offset: float) -> ObjectModel:
    """The catalogue object in other units (x scale) and far away (+ offset along a fixed direction),
    loaded back with load_object (re-centred, 150 mm)."""
    source = catalogue(cls, 3)
    direction = np.array([0.48, -0.6, 0.64])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(source.vertices * scale + offset * direction),
        o3d.utility.Vector3iVector(source.triangles),
    )
    return load_object(mesh, name=f"{cls}-x{scale:g}+{offset:g}")


def input_rounding(scale: float, offset: float) -> float:
    """float64 resolution of the input coordinates, in mm of the loaded (150 mm) object."""
    size = 150.0 * scale
    return float(np.spacing(offset + size)) * 150.0 / size


def check_loaded(cls: str, scale: float, offset: float, planes) -> None:
    reference, model = loaded(cls, 1.0, 0.0), loaded(cls, scale, offset)
    eps = input_rounding(scale, offset) + 1e-13
    assert model.n_vertices == reference.n_vertices
    np.testing.assert_allclose(model.vertices, reference.vertices, rtol=0, atol=2 * eps)
    sensor = FSRSensor(**ODD)
    for i, j in planes:
        c0 = make_contour(reference, plane_of(reference, i, j))
        c1 = make_contour(model, plane_of(model, i, j))
        np.testing.assert_allclose(c1.positions, c0.positions, rtol=0, atol=100 * eps)
        np.testing.assert_allclose(c1.normals, c0.normals, rtol=0, atol=50 * eps)
        s0, s1 = explore(reference, c0, sensor), explore(model, c1, sensor)
        np.testing.assert_array_equal(s1.pad_sides_mm, s0.pad_sides_mm)
        # A hit distance moves by a vertex's shift over the cosine of the incidence, 1 / cos = sqrt(1 + slope^2)
        # with the slope of the surface under the pad read off the reference's own gaps (up to 5 on these rims).
        pitch = s0.pad_sides_mm[:, None, None] / (sensor.cols - 1)
        dy, dx = np.gradient(s0.frames.astype(np.float64), axis=(1, 2))
        oblique = np.sqrt(1.0 + (dx**2 + dy**2) / pitch**2)
        assert np.all(np.abs(s1.frames.astype(np.float64) - s0.frames) <= (LOAD_TOL_MM + 1000 * eps) * oblique)


PLACEMENTS = [(scale, offset) for scale in SCALES for offset in (0.0, OFFSET_MM)]


@pytest.mark.parametrize("scale, offset", PLACEMENTS)
@pytest.mark.parametrize("cls", ["mug", "funnel"])
def test_load_object_makes_units_and_placement_irrelevant(cls, scale, offset):
    check_loaded(cls, scale, offset, [(5, 2000), (17, 4000), (300, 1200)])


@pytest.mark.slow
@pytest.mark.parametrize("scale, offset", PLACEMENTS)
@pytest.mark.parametrize("cls", CLASSES)
def test_load_object_makes_units_and_placement_irrelevant_slow(cls, scale, offset):
    rng = np.random.default_rng(len(cls))
    check_loaded(cls, scale, offset, [tuple(p) for p in rng.integers(10**6, size=(10, 2))])


# --------------------------------------------------------------------- raw models with a scaled sensor
@fast_and_slow(
    6,
    120,
    cls=st.sampled_from(CLASSES),
    seed=st.integers(0, 50),
    i=st.integers(0, 10**6),
    j=st.integers(0, 10**6),
    exponent=st.one_of(st.sampled_from([-3.0, 4.0]), st.floats(-3.0, 4.0)),
    mode=st.sampled_from(["gap", "contact"]),
)
def _scaled_copy_reads_the_same_once_normalised(cls, seed, i, j, exponent, mode):
    base_model = catalogue(cls, seed, 7.5)
    s = 10.0**exponent
    model = ObjectModel(base_model.vertices * s, base_model.triangles, name=f"{cls}x{s:g}")
    base, sensor = base_sensor(mode), scaled_sensor(base_sensor(mode), s)
    try:
        c0 = make_contour(base_model, plane_of(base_model, i, j))
    except ContourError:  # near-collinear or missing draws: the scaled copy must refuse them alike
        with pytest.raises(ContourError):
            make_contour(model, plane_of(model, i, j))
        event("plane refused alike")
        return
    c1 = make_contour(model, plane_of(model, i, j))
    np.testing.assert_allclose(c1.positions / s, c0.positions, rtol=0, atol=1e-12 * base_model.diagonal)
    np.testing.assert_allclose(c1.normals, c0.normals, rtol=0, atol=1e-9)
    s0, s1 = explore(base_model, c0, base), explore(model, c1, sensor)
    np.testing.assert_allclose(s1.pad_sides_mm / s, s0.pad_sides_mm, rtol=1e-12)
    tol = SCALE_TOL * base_model.diagonal
    if mode == "gap":
        np.testing.assert_allclose(s1.frames / np.float32(s), s0.frames, rtol=0, atol=tol)
    else:  # pressure = (stiffness / s) * (indent * s - gap * s): the same; the gap error times the stiffness
        np.testing.assert_allclose(s1.frames, s0.frames, rtol=0, atol=base.stiffness * tol + 2 * 2.0 / 65535)


test_scaled_copy_reads_the_same_once_normalised, test_scaled_copy_reads_the_same_once_normalised_slow = (
    _scaled_copy_reads_the_same_once_normalised
)


def test_a_miss_is_no_surface_whatever_the_range_in_float32():
    """A pad hanging over the bottle's bottom edge (its taxels off the edge miss) settles on the bottom at scale 1
    and at 10**1.5, whose range (15.81... mm) float32 rounds down: the settling fit counted the misses, read at
    that range, as surface 15.8 mm away, rose too far and shrank the pad to 0.64 of its side instead. Found by the
    slow property above; a fixed case here."""
    base_model = catalogue("bottle", 0, 7.5)
    s = 10.0**1.5
    model = ObjectModel(base_model.vertices * s, base_model.triangles, name="bottle x31.6")
    sensor = scaled_sensor(base_sensor("gap"), s)
    assert float(np.float32(sensor.range_mm)) < sensor.range_mm
    c0, c1 = make_contour(base_model, plane_of(base_model, 0, 1)), make_contour(model, plane_of(model, 0, 1))
    s0, s1 = explore(base_model, c0, base_sensor("gap")), explore(model, c1, sensor)
    assert s0.pad_sides_mm[12] == base_sensor().side_mm  # settled on the bottom, not shrunk
    np.testing.assert_allclose(s1.pad_sides_mm / s, s0.pad_sides_mm, rtol=1e-12)


@pytest.mark.parametrize("standoff, range_", [(5.1, 15.811388300841896), (4.9, 12.7), (5.0, 10.0)])
def test_misses_and_inside_starts_give_no_height_whatever_their_float32(standoff, range_):
    """The gaps of a ray that started inside (-standoff) or missed (range) are float32: neither is surface, whether
    the setting rounds up or down in float32 (5.1 and 15.81 round down, 4.9 and 12.7 up, 5 and 10 are exact)."""
    sensor = FSRSensor(standoff_mm=standoff, range_mm=range_)
    inside, miss = -np.float32(standoff), np.float32(range_)
    gaps = np.array([[inside, miss, 0.0, -0.5 * standoff, 0.99 * range_]], dtype=np.float32).astype(np.float64)
    assert sensor._surface_found(gaps).tolist() == [[False, False, True, True, True]]


def test_the_sensor_cannot_be_scaled_past_its_length_cap():
    # The default sensor scaled with a 1e4-times object would need a 2e5 mm pad: refused (the base above is
    # 1/20 of the default for this reason). load_object(size_mm=...) is the way to bring such objects in.
    with pytest.raises(SensorSpecError, match="side_mm"):
        scaled_sensor(FSRSensor(), 1e4)
    assert scaled_sensor(base_sensor(), 1e4).side_mm == pytest.approx(1e4)


# ------------------------------------------------------------------------------- far from the origin
def far_copy(model: ObjectModel, seed: int) -> tuple[ObjectModel, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    d *= OFFSET_MM / np.linalg.norm(d)
    return ObjectModel(model.vertices + d, model.triangles, name=f"{model.name}-far"), d


def contact_cases(classes, seeds):
    return [(c, s) for c in classes for s in seeds]


@pytest.mark.parametrize("cls, seed", contact_cases(CLASSES[::3], [0]))
def test_far_object_keeps_every_probe_in_contact(cls, seed):
    model = catalogue(cls, seed)
    far, d = far_copy(model, seed)
    resolution = float(np.spacing(np.float32(np.abs(far.vertices).max())))  # 0.0625 mm at 1e6 mm
    sensor = FSRSensor(**ODD)
    # Without settling every pad stays on its probe, so its centre taxel must touch.
    contact = FSRSensor(mode="contact", indent_mm=4 * resolution, saturation=1.0, settle_mm=0.0, **ODD)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        i, j = rng.integers(model.n_vertices, size=2)
        c0, c1 = make_contour(model, plane_of(model, i, j)), make_contour(far, plane_of(far, i, j))
        # The geometry is float64: contours of the far copy are the near ones moved (float64 rounding at 1e6).
        np.testing.assert_allclose(c1.positions - d, c0.positions, rtol=0, atol=1e-8)
        near_gaps = sensor.measure_gaps(model, c0.positions, c0.normals, c0.tangents, sensor.side_mm)
        far_gaps = sensor.measure_gaps(far, c1.positions, c1.normals, c1.tangents, sensor.side_mm)
        assert np.abs(near_gaps[:, CENTRE, CENTRE]).max() < 1e-5
        assert np.abs(far_gaps[:, CENTRE, CENTRE]).max() <= 2 * resolution
        frames, _ = contact.press(far, c1.positions, c1.normals, c1.tangents)
        assert (frames[:, CENTRE, CENTRE] > 0).all()  # every probe touches


@pytest.mark.parametrize("cls", ["bowl", "funnel"])
def test_far_object_reads_the_same_frames(cls):
    model = catalogue(cls, 0)
    far, _ = far_copy(model, 1)
    sensor = FSRSensor(**ODD)
    rng = np.random.default_rng(4)
    for _ in range(3):
        i, j = rng.integers(model.n_vertices, size=2)
        s0 = explore(model, make_contour(model, plane_of(model, i, j)), sensor)
        s1 = explore(far, make_contour(far, plane_of(far, i, j)), sensor)
        np.testing.assert_array_equal(s1.pad_sides_mm, s0.pad_sides_mm)
        np.testing.assert_allclose(s1.frames, s0.frames, rtol=0, atol=LOAD_TOL_MM)
