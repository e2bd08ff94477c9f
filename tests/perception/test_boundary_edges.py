"""Edges of the hostile-input checks: an existing output file may be replaced (the write test runs in its folder,
not on it); look_at refuses a non-finite up vector and names an overflowing distance; a mesh file of exactly the
size limit and a PNG of exactly its bound are not refused from their size."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from perception.atomic import check_output_file
from perception.camera import Intrinsics, RGBDFrame, look_at, read_recording, write_recording
from perception.camera.recording import PNG_SPARE_BYTES
from perception.errors import InvalidArgumentError, MeshLoadError
from perception.geometry import load_object


def test_an_existing_output_file_can_be_replaced(tmp_path):
    out = tmp_path / "model.vtm"
    out.write_bytes(b"old")
    assert check_output_file(out) == out
    assert out.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [out]


@pytest.mark.parametrize("up", [[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0]])
def test_look_at_with_a_non_finite_up_is_refused(up):
    with pytest.raises(InvalidArgumentError, match="must be finite"):
        look_at([100.0, 0.0, 50.0], [0.0, 0.0, 0.0], up)


def test_look_at_from_a_finite_but_overflowing_eye_names_the_distance():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidArgumentError, match="too far from its target"):
            look_at([1e200, 1e200, 1e200], [0.0, 0.0, 0.0])


@pytest.mark.parametrize("suffix", [".off", ".stl"])
def test_a_mesh_file_of_exactly_the_limit_passes_the_size_check(tmp_path, monkeypatch, suffix):
    monkeypatch.setenv("VISUOTACTILE_MAX_FILE_MB", "2")
    path = tmp_path / f"edge{suffix}"
    with open(path, "wb") as f:
        f.truncate(2 * 2**20)
    with pytest.raises(MeshLoadError) as info:  # garbage: refused by the parser, not by the size check
        load_object(path)
    assert "limit" not in str(info.value)


@pytest.mark.parametrize("image", ["color", "depth"])
def test_a_png_of_exactly_its_bound_is_not_refused_from_its_size(tmp_path, image):
    frame = RGBDFrame(np.full((24, 32, 3), 128, np.uint8), np.full((24, 32), 500.0, np.float32),
                      Intrinsics(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24), np.eye(4), 0.0, name="f")
    rec = write_recording(tmp_path / "rec", [frame])
    (path,) = [p for p in rec.iterdir() if p.suffix == ".png" and image in p.name]
    with open(path, "r+b") as f:
        f.truncate((32 * 8 + 1) * 24 + PNG_SPARE_BYTES)  # zeros after IEND
    assert len(read_recording(rec)) == 1
