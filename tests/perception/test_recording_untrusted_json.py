"""Recordings are files users exchange: JSON nested beyond the parser's recursion limit, JSON files far larger
than any recording's metadata, and files that are symbolic links out of the recording folder are refused as
DatasetError naming the file (one error line on the command line)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from perception.camera import Intrinsics, RGBDFrame, read_recording, write_recording
from perception.camera.recording import MAX_JSON_BYTES
from perception.errors import DatasetError

DEEP = "[" * 100_000 + "]" * 100_000


@pytest.fixture
def recording(tmp_path) -> Path:
    color = np.full((24, 32, 3), 128, np.uint8)
    depth = np.full((24, 32), 500.0, np.float32)
    depth[8:16, 10:22] = 450.0
    frame = RGBDFrame(color, depth, Intrinsics(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24), np.eye(4),
                      0.0, name="f")
    return write_recording(tmp_path / "rec", [frame])


def _frame_json(folder: Path) -> Path:
    return folder / "frame_000000.json"


@pytest.mark.parametrize("which", ["recording.json", "frame", "camera.json"])
def test_deeply_nested_json_is_a_dataset_error_naming_the_file(recording, which):
    if which == "recording.json":
        path = recording / "recording.json"
    elif which == "frame":
        path = _frame_json(recording)
    else:  # the generic capture layout
        (recording / "recording.json").unlink()
        path = recording / "camera.json"
    path.write_text('{"a": ' + DEEP + "}")
    with pytest.raises(DatasetError, match=rf"{path.name}: cannot read JSON \(JSON nested too deeply\)"):
        read_recording(recording)


def test_deeply_nested_json_is_one_line_on_the_command_line(recording, tmp_path, capsys):
    _frame_json(recording).write_text(DEEP)
    capsys.readouterr()
    assert main(["camera", "--source", str(recording), "--out", str(tmp_path / "out"), "--views", "1",
                 "--contours", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frame_000000.json" in err[0] and "nested too deeply" in err[0], err


def test_an_oversized_frame_json_is_refused_from_its_size(recording):
    # Valid JSON (trailing white space), 8 MiB: read whole before; refused from st_size now (a 2 GiB sparse file
    # would be refused the same way, without reading a byte).
    path = _frame_json(recording)
    with open(path, "a") as f:
        f.write(" " * (8 * 2**20))
    assert path.stat().st_size > MAX_JSON_BYTES
    with pytest.raises(DatasetError, match=rf"frame_000000\.json: cannot read JSON \({path.stat().st_size} bytes, more than the "
                                           rf"{MAX_JSON_BYTES}"):
        read_recording(recording)



@pytest.mark.parametrize("image,what", [("color", "colour"), ("depth", "depth")])
def test_a_png_far_larger_than_its_pixels_is_refused_undecoded(recording, image, what):
    """A 32 x 24 image followed by 8 MiB of other bytes (a sparse tail): refused from the file's size, which no
    image of that size can need, before PIL decodes anything."""
    from perception.camera.recording import PNG_SPARE_BYTES

    (path,) = [p for p in recording.iterdir() if p.suffix == ".png" and image in p.name]
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size + 8 * 2**20)
    most = (32 * 8 + 1) * 24 + PNG_SPARE_BYTES
    with pytest.raises(DatasetError, match=rf"{path.name}: {what} image file of \d+ bytes, more than a 32 x 24 image "
                                           rf"can take \({most}\)"):
        read_recording(recording)

def test_an_oversized_sparse_frame_json_is_refused_without_reading(recording, monkeypatch):
    path = _frame_json(recording)
    with open(path, "r+b") as f:
        f.truncate(2 << 30)  # 2 GiB, nothing on disk
    reads = []
    real_open = open

    class Spy:
        def __init__(self, handle):
            self.handle = handle

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

        def __getattr__(self, name):
            return getattr(self.handle, name)

        def read(self, *args):
            reads.append(args)
            return self.handle.read(*args)

    def spy(file, *args, **kwargs):
        handle = real_open(file, *args, **kwargs)
        return Spy(handle) if Path(file) == path else handle

    monkeypatch.setattr("builtins.open", spy)
    monkeypatch.setattr(Path, "read_text", lambda *a, **k: pytest.fail("read whole"))
    with pytest.raises(DatasetError, match="bytes, more than the"):
        read_recording(recording)
    assert reads == []  # the size was checked, not the content


@pytest.mark.parametrize("member", ["frame_000000.json", "frame_000000.color.png", "frame_000000.depth.png"])
def test_files_linking_outside_the_recording_are_refused(recording, tmp_path, member):
    # The link's target is a valid copy of the file: only where it lies is wrong.
    outside = tmp_path / "elsewhere" / member
    outside.parent.mkdir()
    shutil.copy(recording / member, outside)
    (recording / member).unlink()
    os.symlink(outside, recording / member)
    with pytest.raises(DatasetError, match=rf"{member}: leads outside the recording folder"):
        read_recording(recording)


def test_links_inside_the_recording_folder_are_read(recording):
    inside = recording / "meta" / "f.json"
    inside.parent.mkdir()
    shutil.move(_frame_json(recording), inside)
    os.symlink(Path("meta") / "f.json", _frame_json(recording))
    (frame,) = read_recording(recording)
    assert frame.depth_mm.shape == (24, 32)
    # A recording folder reached through a link is read too (the link is the folder, not a file in it).
    os.symlink(recording, recording.parent / "alias")
    assert len(read_recording(recording.parent / "alias")) == 1


def test_an_index_listing_many_frames_is_within_its_bound(recording):
    # The index's bound grows with the frames limit: an index of 10,000 long names is still read (and its frames
    # reported missing), not refused for its size.
    names = [f"f{i:06d}_" + "x" * 190 for i in range(10_000)]
    index = recording / "recording.json"
    index.write_text(json.dumps({"format": "visuotactile-rgbd/1", "frames": names, "depth_scale": 1000.0},
                                indent=1))
    assert index.stat().st_size > MAX_JSON_BYTES
    with pytest.raises(DatasetError, match="frame metadata is missing"):
        read_recording(recording)
