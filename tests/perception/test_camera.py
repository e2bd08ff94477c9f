"""RGB-D frames, recordings, the virtual OAK's stereo model, and the OAK's no-device path."""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import pytest

from perception.camera import (
    Intrinsics,
    OakCamera,
    RGBDFrame,
    StereoNoise,
    VirtualOakCamera,
    look_at,
    read_recording,
    write_recording,
)
from perception.errors import DatasetError, DeviceNotFoundError, InvalidArgumentError
from perception.shapes import make_object
from tests.conftest import data_folder


@pytest.fixture(scope="module")
def box():
    return make_object("box", 0)


@pytest.fixture(scope="module")
def box_frames(box):
    return VirtualOakCamera(box, seed=3).capture_views(2, 500.0)


# ----------------------------------------------------------------------------------------- frames
def test_intrinsics_and_frame_validation():
    k = Intrinsics(500.0, 500.0, 31.5, 23.5, 64, 48)
    assert np.allclose(k.matrix, [[500, 0, 31.5], [0, 500, 23.5], [0, 0, 1]])
    with pytest.raises(InvalidArgumentError, match="focal"):
        Intrinsics(0.0, 500.0, 1.0, 1.0, 64, 48)
    color, depth = np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 500.0)
    with pytest.raises(InvalidArgumentError, match="cam7: depth must be"):
        RGBDFrame(color, depth[:10], k, name="cam7")
    with pytest.raises(InvalidArgumentError, match="finite and >= 0"):
        RGBDFrame(color, np.where(depth > 0, np.nan, 0), k)
    with pytest.raises(InvalidArgumentError, match="rigid"):
        RGBDFrame(color, depth, k, pose=np.diag([2.0, 1, 1, 1]))
    frame = RGBDFrame(color, depth, k)
    with pytest.raises(ValueError):  # read-only arrays: a frame is a record of what was captured
        frame.depth_mm[0, 0] = 1.0


def test_back_projection_of_a_known_pixel():
    k = Intrinsics(400.0, 300.0, 10.0, 5.0, 21, 11)
    depth = np.zeros((11, 21))
    depth[7, 18] = 800.0  # column 18, row 7
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    frame = RGBDFrame(np.zeros((11, 21, 3), np.uint8), depth, k, pose)
    (point,), _ = frame.points()
    # x = (u - cx) z / fx = 8 * 800 / 400 = 16; y = (v - cy) z / fy = 2 * 800 / 300; plus the translation.
    assert np.allclose(point, [17.0, 2.0 + 1600 / 300, 803.0])


# ------------------------------------------------------------------------------------- recordings
def test_recording_round_trip_is_identical(tmp_path, box_frames):
    write_recording(tmp_path / "rec", box_frames, source="virtual")
    back = read_recording(tmp_path / "rec")
    assert len(back) == len(box_frames)
    for a, b in zip(box_frames, back):
        assert a.color.tobytes() == b.color.tobytes()
        assert a.depth_mm.tobytes() == b.depth_mm.tobytes()
        assert a.intrinsics == b.intrinsics
        assert a.pose.tobytes() == b.pose.tobytes()
        assert a.timestamp_s == b.timestamp_s
    index = json.loads((tmp_path / "rec" / "recording.json").read_text())
    assert index["frames"] == ["frame_000000", "frame_000001"] and index["depth_scale"] == 1000.0


def test_recording_rounds_sub_millimetre_depth_and_refuses_overflow(tmp_path):
    k = Intrinsics(100.0, 100.0, 1.5, 1.5, 4, 4)
    depth = np.full((4, 4), 500.4)
    write_recording(tmp_path / "a", [RGBDFrame(np.zeros((4, 4, 3), np.uint8), depth, k)])
    assert np.all(read_recording(tmp_path / "a")[0].depth_mm == 500.0)
    write_recording(tmp_path / "b", [RGBDFrame(np.zeros((4, 4, 3), np.uint8), depth, k)], depth_scale=10000.0)
    assert np.allclose(read_recording(tmp_path / "b")[0].depth_mm, 500.4, atol=1e-4)
    with pytest.raises(DatasetError, match="beyond 16 bits"):
        write_recording(tmp_path / "c", [RGBDFrame(np.zeros((4, 4, 3), np.uint8), depth * 200, k)])


def test_bad_recordings_raise(tmp_path, box_frames):
    with pytest.raises(DatasetError, match="no such recording folder"):
        read_recording(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="not a recording"):
        read_recording(tmp_path / "empty")
    write_recording(tmp_path / "rec", box_frames[:1])
    (tmp_path / "rec" / "frame_000000.depth.png").unlink()
    with pytest.raises(DatasetError, match="frame_000000.depth.png: depth image is missing"):
        read_recording(tmp_path / "rec")
    (tmp_path / "rec" / "frame_000000.depth.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="cannot read depth image"):
        read_recording(tmp_path / "rec")
    with pytest.raises(DatasetError, match="no frames"):
        write_recording(tmp_path / "none", [])


def test_reads_the_graspnet_realsense_capture():
    folder = data_folder("rgbd/graspnet_tabletop")
    from PIL import Image

    (frame,) = read_recording(folder)
    camera = json.loads((folder / "camera.json").read_text())
    assert frame.intrinsics.fx == camera["fx"] and frame.intrinsics.cy == camera["cy"]
    assert (frame.intrinsics.width, frame.intrinsics.height) == (1280, 720)
    raw = np.asarray(Image.open(folder / "depth.png")).astype(np.float64)
    assert np.array_equal(frame.depth_mm, raw * 1000.0 / camera["depth_scale"])  # png units are mm
    assert np.array_equal(frame.color, np.asarray(Image.open(folder / "color.png").convert("RGB")))


# ------------------------------------------------------------------------------------- virtual OAK
def _table_depth(camera: VirtualOakCamera, pose: np.ndarray) -> np.ndarray:
    """Analytic z depth of the table plane z = 0 at every pixel (inf where the ray misses it)."""
    k = camera.intrinsics
    rows, cols = np.mgrid[0 : k.height, 0 : k.width]
    d = np.stack([(cols - k.cx) / k.fx, (rows - k.cy) / k.fy, np.ones(cols.shape)], -1) @ pose[:3, :3].T
    with np.errstate(divide="ignore"):
        t = -pose[2, 3] / d[..., 2]
    return np.where(t > 0, t, np.inf)


def test_oak_geometry_and_minimum_range(box):
    cam = VirtualOakCamera(box, mode="800p")
    assert (cam.intrinsics.width, cam.intrinsics.height, cam.intrinsics.fx) == (1280, 800, 882.5)
    assert cam.min_range_mm == pytest.approx(882.5 * 75 / 95)
    assert VirtualOakCamera(box, mode="800p", extended_disparity=True).min_range_mm == pytest.approx(882.5 * 75 / 190)
    close = VirtualOakCamera(box, noise=None)  # 400p: minimum range 348 mm
    frame = close.capture(close.orbit_poses(1, 300.0, 30.0)[0])
    valid = frame.depth_mm[frame.valid]
    assert valid.min() >= close.min_range_mm - 1 and (frame.depth_mm == 0).mean() > 0.2


def test_noiseless_depth_is_the_table_distance_rounded_to_millimetres(box):
    cam = VirtualOakCamera(box, noise=None)
    pose = cam.orbit_poses(1, 600.0, 40.0)[0]
    frame = cam.capture(pose)
    analytic = _table_depth(cam, pose)
    # Table pixels: those whose analytic depth is where the camera measured (the object hides the rest).
    table = frame.valid & np.isfinite(analytic) & (np.abs(frame.depth_mm - analytic) < 1.0)
    assert table.mean() > 0.5
    assert np.abs(frame.depth_mm[table] - np.rint(analytic[table])).max() <= 1.0
    assert np.all(frame.depth_mm == np.rint(frame.depth_mm))


def test_depth_noise_grows_with_the_square_of_the_distance(box):
    noise = StereoNoise(disparity_sigma_px=0.15, subpixel_bits=5, edge_jump=0.0, occlusion=False)
    stds = []
    for distance in (450.0, 900.0):
        pose = look_at([0.0, -0.3 * distance, distance], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
        cam = VirtualOakCamera(box, noise=noise, seed=1)
        frame = cam.capture(pose)
        exact = VirtualOakCamera(box, noise=None).capture(pose)
        analytic = _table_depth(cam, pose)
        # Table pixels (the exact capture sees the plane there), away from the object's outline.
        table = frame.valid & exact.valid & (np.abs(exact.depth_mm - analytic) <= 0.5)
        z = analytic[table]
        fb = cam.intrinsics.fx * cam.baseline_mm
        # Expected: disparity noise and its quantisation mapped through dZ = Z^2 / (f B) dd, plus mm rounding.
        sigma_d2 = noise.disparity_sigma_px**2 + (2.0**-noise.subpixel_bits) ** 2 / 12
        expected = np.sqrt(np.mean((z**2 / fb) ** 2) * sigma_d2 + 1 / 12)
        measured = np.std(frame.depth_mm[table] - z)
        assert measured == pytest.approx(expected, rel=0.1)
        stds.append(measured)
    assert stds[1] / stds[0] == pytest.approx(4.0, rel=0.25)


def test_occlusion_shadows_lie_along_the_baseline_beside_nearer_surfaces(box):
    pose = VirtualOakCamera(box).orbit_poses(1, 500.0, 30.0)[0]
    capture = lambda **kw: VirtualOakCamera(box, noise=StereoNoise(0.0, 3, **kw)).capture(pose)
    seen = capture(edge_jump=0.0, occlusion=False)
    stereo = capture(edge_jump=0.0)
    edges = capture()
    shadow = seen.valid & ~stereo.valid
    assert shadow.sum() > 100 and not (stereo.valid & ~seen.valid).any()
    assert (seen.valid & ~edges.valid).sum() > shadow.sum()  # depth edges remove more
    # The mono cameras sit left and right of the colour camera: a pixel is hidden from one of them by a
    # nearer surface in the same image row, at most f B (1/z_near - 1/z_far) < 60 px away. Nearer by more than
    # the 1 mm depth step: a few shadows fall behind the box's own bevel, only 5-10 mm nearer.
    depth = seen.depth_mm
    for row, col in zip(*np.nonzero(shadow)):
        window = depth[row, max(col - 60, 0) : col + 61]
        assert ((window > 0) & (window < depth[row, col] - 2.0)).any()


def test_same_seed_same_bytes_other_seed_other_noise(box):
    pose = VirtualOakCamera(box).orbit_poses(1)[0]
    a = VirtualOakCamera(box, seed=5).capture(pose, 2)
    b = VirtualOakCamera(box, seed=5).capture(pose, 2)
    c = VirtualOakCamera(box, seed=6).capture(pose, 2)
    assert a.depth_mm.tobytes() == b.depth_mm.tobytes() and a.color.tobytes() == b.color.tobytes()
    assert a.depth_mm.tobytes() != c.depth_mm.tobytes()


def test_virtual_camera_rejects_bad_requests(box):
    with pytest.raises(InvalidArgumentError, match="unknown mode"):
        VirtualOakCamera(box, mode="4k")
    with pytest.raises(InvalidArgumentError, match="n_views"):
        VirtualOakCamera(box).orbit_poses(0)
    with pytest.raises(InvalidArgumentError, match="elevation"):
        VirtualOakCamera(box).orbit_poses(2, 500.0, 90.0)


# --------------------------------------------------------------------------------------- live OAK
def test_no_oak_raises_device_not_found_within_seconds(no_oak):
    start = time.monotonic()
    with pytest.raises(DeviceNotFoundError, match="no device found") as info, OakCamera():
        pass
    assert time.monotonic() - start < 5.0
    assert "recording" in str(info.value)


def test_missing_depthai_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "depthai", None)  # import depthai -> ImportError
    with pytest.raises(DeviceNotFoundError, match=r"depthai is not installed.*visuotactile\[camera\]"):
        OakCamera().open()


def test_capture_before_open_is_refused():
    with pytest.raises(DeviceNotFoundError, match="not open"):
        OakCamera().capture()
