"""A refusal is one stderr line: no numpy RuntimeWarning printed before it. Through a fresh process, as a user runs
it (pytest's own warning capture would hide the warnings), and in-process with warnings as errors."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

from perception.camera import VirtualOakCamera, look_at
from perception.camera.virtual import MAX_DISTANCE_MM
from perception.errors import InvalidArgumentError
from perception.shapes import make_object


def test_camera_distance_near_float_max_is_one_line(tmp_path):
    # --distance 1e308 passed the finite-positive check; look_at overflowed (RuntimeWarning: overflow) first.
    done = subprocess.run([sys.executable, "-m", "fusion.cli", "camera", "--source", "virtual:box", "--views", "1",
                           "--contours", "1", "--distance", "1e308", "--out", str(tmp_path / "cam"), "--no-progress"],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--distance" in lines[0] and f"{MAX_DISTANCE_MM:g}" in lines[0], done.stderr
    assert not (tmp_path / "cam").exists()


@pytest.mark.parametrize("distance", [1e308, 1e200, MAX_DISTANCE_MM * 1.001])
def test_orbit_beyond_the_camera_range_is_refused_without_warnings(distance):
    camera = VirtualOakCamera(make_object("box", 0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidArgumentError, match="distance_mm"):
            camera.orbit_poses(1, distance)
    assert len(camera.orbit_poses(1, MAX_DISTANCE_MM)) == 1


@pytest.mark.parametrize("eye", [[1e308, 1e308, 1e308], [np.inf, 0.0, 0.0], [np.nan, 0.0, 0.0]])
def test_look_at_from_an_overflowing_or_non_finite_eye_is_refused_without_warnings(eye):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidArgumentError, match="look_at"):
            look_at(eye, [0.0, 0.0, 0.0])


def test_svm_model_with_zero_scale_is_one_line(tmp_path):
    """A model file (valid checksum) whose standardiser scale_ is 0 is refused ("steps do not fit together") with
    nothing but that line on stderr (its probe prediction divides by the zero scale)."""
    import json

    from safetensors import safe_open
    from safetensors.numpy import save

    from fusion.cli import main
    from fusion.modelfile import FORMAT_NAME, content_digest
    from tactile.dataset import generate
    from tactile.sensor import FSRSensor

    store = tmp_path / "s.zarr"
    generate([("box", 0), ("ring", 0)], store, strategies="blind", contours_per_object=6,
             sensor=FSRSensor(rows=8, cols=8), probes=6, seed=0, workers=1, progress=False)
    path = tmp_path / "svm.vtm"
    assert main(["train", "--store", str(store), "--model", "svm", "--out", str(path), "--split", "none",
                 "--no-progress"]) == 0
    with safe_open(str(path), framework="numpy") as f:
        description = json.loads(f.metadata()[FORMAT_NAME].partition(" ")[2])
        arrays = {k: f.get_tensor(k) for k in list(f.keys())}
    arrays["pipeline.standardise.scale_"] = np.zeros_like(arrays["pipeline.standardise.scale_"])
    arrays = {k: np.array(v, order="C", copy=True) for k, v in arrays.items()}
    text = json.dumps(description)
    path.write_bytes(save(arrays, metadata={FORMAT_NAME: f"{content_digest(text, arrays)} {text}"}))
    proc = subprocess.run([sys.executable, "-m", "fusion.cli", "evaluate", "--model", str(path), "--store", str(store),
                           "--no-progress"], check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
