"""``visuotactile camera``: the no-device path, virtual and recorded sources, bad sources."""

from __future__ import annotations

import json
import time

import pytest

from fusion.cli import build_parser, main
from perception.camera import find_oak_devices
from perception.errors import DeviceNotFoundError
from tests.conftest import data_folder


def test_oak_without_a_device_exits_non_zero_within_5_s_and_says_what_to_do(capsys):
    try:
        if find_oak_devices():
            pytest.skip("an OAK is connected")
    except DeviceNotFoundError:
        pass
    build_parser()  # imports every subcommand module once: that start-up cost is not the camera's
    start = time.monotonic()
    code = main(["camera", "--source", "oak"])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert code == 2 and elapsed < 5.0
    assert "no OAK device found" in err and "--source <recording folder>" in err
    assert len(err.strip().splitlines()) == 1 or "depthai" in err  # one line (+ depthai's own USB warning)


def test_virtual_source_reconstructs_touches_and_writes_a_figure(tmp_path, capsys):
    code = main(["camera", "--source", "virtual:bottle", "--views", "1", "--contours", "3", "--json",
                 "--out", str(tmp_path)])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 1 and summary["true_class"] == "bottle"
    # (Accuracy with 4 views is checked in tests/perception/test_reconstruct_scenes.py.)
    assert 0 < summary["reconstruction"]["error_mm"]["mean_mm"] < 1.0
    assert summary["sequences"] == 3 and summary["probes"] == 25 and summary["prediction"] is None
    png = (tmp_path / "camera.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert json.loads((tmp_path / "summary.json").read_text())["sequences"] == 3


def test_recording_folder_source(tmp_path, capsys):
    folder = data_folder("rgbd/graspnet_tabletop")
    assert main(["camera", "--source", str(folder), "--contours", "2", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "1 frame(s)" in out and "touched: 2 contours x 25 probes" in out
    assert "recognition skipped" in out


@pytest.mark.parametrize(
    "source,message",
    [("virtual:teapot", "unknown object class 'teapot'"), ("/no/such/folder", "not virtual:<class>, oak")],
)
def test_bad_sources_are_one_line_errors(source, message, capsys):
    assert main(["camera", "--source", source, "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("visuotactile camera: error:")


@pytest.mark.slow
def test_camera_demo_example_runs(capsys, monkeypatch):
    import runpy
    import sys
    from pathlib import Path

    monkeypatch.setattr(sys, "argv", ["camera_demo.py"])  # no model: everything up to the tactile batch
    runpy.run_path(str(Path(__file__).resolve().parents[2] / "examples" / "camera_demo.py"), run_name="__main__")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("reconstructed") and "mean error" in lines[0]
    assert float(lines[0].split("mean error ")[1].split(" mm")[0]) < 1.0
    assert lines[1] == "(4, 25, 32, 32)"
