"""Hostile and careless inputs through the command line: damaged or edited stores, hostile model files, recordings,
bad options and output paths, racing and killed runs. Each ends in one line on stderr and exit 2 (or works where it
should), counts are refused before anything is allocated, and nothing outside the given files is read or run.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from perception.limits import LIMITS
from tactile.dataset import generate
from tactile.sensor import FSRSensor
from tests._model_files import rewrite
from tests._small_store import small_knn_model, small_store

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return small_store(tmp_path_factory.mktemp("boundaries") / "small.zarr")


@pytest.fixture(scope="module")
def model(store, tmp_path_factory) -> Path:
    return small_knn_model(store, tmp_path_factory.mktemp("boundaries-model") / "knn.vtm")


def one_line(capsys, code: int, argv: list[str], *expect: str) -> str:
    """Run the CLI; assert exit ``code`` and, for 2, exactly one line on stderr holding every ``expect``."""
    capsys.readouterr()
    assert main(argv) == code
    err = capsys.readouterr().err.strip().splitlines()
    if code == 2:
        assert len(err) == 1, err
        for text in expect:
            assert text in err[0], err[0]
        return err[0]
    return "\n".join(err)


def edited_store(store: Path, tmp_path: Path, edit) -> Path:
    copy = tmp_path / "edited.zarr"
    shutil.copytree(store, copy)
    meta = json.loads((copy / "zarr.json").read_text())
    edit(meta["attributes"], meta["attributes"]["visuotactile_dataset"]["settings"])
    (copy / "zarr.json").write_text(json.dumps(meta))
    return copy


def _set(key, value):
    def edit(attrs, settings):
        settings[key] = value
    return edit


def _drop(key):
    return lambda attrs, settings: settings.pop(key)


STORE_EDITS = {
    "metadata is a list": (lambda a, s: a.__setitem__("visuotactile_dataset", [1, 2]), "not a visuotactile"),
    "no settings": (lambda a, s: a["visuotactile_dataset"].pop("settings"), "'settings' must be an object"),
    "no probes": (_drop("probes"), "'probes' must be an integer"),
    "no sensor": (_drop("sensor"), "'sensor' must be"),
    "non-numeric count": (_set("contours_per_object", "many"), "'contours_per_object' must be an integer"),
    "float count": (_set("contours_per_object", 1e8), "'contours_per_object' must be an integer"),
    "settings say 10 probes, arrays hold 6": (_set("probes", 10), "the 'frames' array is uint16 (12, 6, 8, 8)"),
    "contours 1e8": (_set("contours_per_object", 10**8), "VISUOTACTILE_MAX_CONTOURS"),
    "label not in class_names": (_set("class_names", ["box"]), "label 'ring', which is not in class_names"),
    "objects is text": (_set("objects", "box"), "'objects' must be a list"),
    "repeated objects": (lambda a, s: s.__setitem__("objects", s["objects"] * 2), "object names must be distinct"),
    "scale is text": (lambda a, s: s["encoding"].__setitem__("scale", "x"), "encoding 'scale'"),
    "huge taxel grid": (lambda a, s: s["sensor"].__setitem__("rows", 10**6), "VISUOTACTILE_MAX_TAXELS"),
}


@pytest.mark.parametrize("case", sorted(STORE_EDITS))
def test_edited_store_metadata_is_one_line_and_exit_2(store, model, tmp_path, capsys, case):
    edit, message = STORE_EDITS[case]
    edited = edited_store(store, tmp_path, edit)
    one_line(capsys, 2, ["evaluate", "--model", str(model), "--store", str(edited)], str(edited), message)


def test_store_without_its_normals_array_is_refused(store, model, tmp_path, capsys):
    copy = tmp_path / "no-normals.zarr"
    shutil.copytree(store, copy)
    shutil.rmtree(copy / "normals")
    one_line(capsys, 2, ["evaluate", "--model", str(model), "--store", str(copy)], "'normals' array")


def test_deleted_frames_shard_never_evaluates(store, model, tmp_path, capsys):
    copy = tmp_path / "damaged.zarr"
    shutil.copytree(store, copy)
    shard = sorted((copy / "frames").rglob("c/*/0/0/0"))[1]
    shard.unlink()
    one_line(capsys, 2, ["evaluate", "--model", str(model), "--store", str(copy)], "'ring/0' is damaged")


# ------------------------------------------------------------------------------------------------ model files
def _rewrite_model(src: Path, dst: Path, description) -> Path:
    """``src`` with its description replaced by ``description(original)``, resealed."""
    return rewrite(src, dst, replace=description)


MODEL_EDITS = {
    "description null": (lambda d: None, "model description is missing"),
    "description a string": (lambda d: "knn", "model description is missing"),
    "no classes": (lambda d: {k: v for k, v in d.items() if k != "classes"}, "classes"),
    "empty classes": (lambda d: {**d, "classes": []}, "classes"),
    "unfitted": (lambda d: {**d, "state": None}, "state"),
}


@pytest.mark.parametrize("case", sorted(MODEL_EDITS))
def test_hostile_model_headers_are_one_line_and_exit_2(store, model, tmp_path, capsys, case):
    edit, message = MODEL_EDITS[case]
    path = _rewrite_model(model, tmp_path / "edited.vtm", edit)
    one_line(capsys, 2, ["evaluate", "--model", str(path), "--store", str(store)], str(path), message)


def test_pickled_model_never_runs_its_payload(store, tmp_path, capsys):
    marker = tmp_path / "ran"
    payload = tmp_path / "evil.pkl"
    # A pickle whose loading would create ``marker``: os.system("touch marker").
    payload.write_bytes(b"cos\nsystem\n(V" + f"touch {marker}".encode() + b"\ntR.")
    one_line(capsys, 2, ["evaluate", "--model", str(payload), "--store", str(store)], "pickle")
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------- options
def test_bad_options_are_one_line_and_exit_2(store, model, tmp_path, capsys):
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    folder = tmp_path / "folder"
    for cls, size in (("Cup", 10), ("Mug", 20)):  # a mesh set: --classes Cup names a class that exists
        (folder / "meshes" / cls).mkdir(parents=True)
        (folder / "meshes" / cls / "a.off").write_text(_box_off(10, 10, size))
    ev = ["evaluate", "--model", str(model), "--store", str(store)]
    tr = ["train", "--store", str(store), "--model", "knn", "--split", "none"]
    cases = [
        (ev + ["--touches", "-2"], "argument --touches: must be a positive integer"),
        (ev + ["--touches", "0"], "argument --touches: must be a positive integer"),
        (ev + ["--touches", "100000000"], "VISUOTACTILE_MAX_TOUCHES"),
        (ev + ["--seed", "-1"], "--seed must be a non-negative integer"),
        (ev + ["--figure", str(tmp_path / "out.txt")], "give a file ending in .png"),
        (ev + ["--figure", str(folder)], "is a folder"),
        (tr + ["--out", str(folder)], "is a folder"),
        (tr + ["--out", str(a_file / "x.pkl")], "is a file, not a folder"),
        (tr + ["--out", ""], "an empty path"),
        (tr + ["--out", str(tmp_path / ("m" * 250 + ".vtm"))], "the name is too long"),
        (tr + ["--out", str(tmp_path / "m.vtm"), "--seed", "-1"], "--seed must be a non-negative integer"),
        (["recognize", str(tmp_path / "x.off"), "--model", str(model), "--seed", "-1"], "--seed"),
        (["recognize", str(tmp_path / "x.off"), "--model", str(model), "--touches", "100000000"],
         "VISUOTACTILE_MAX_TOUCHES"),
        (["generate", "--catalogue", "1", "--classes", "box", "ring", "--out", str(tmp_path / "t.zarr"),
          "--timeout", "0"], "--timeout"),
        (["generate", "--catalogue", "1", "--classes", "box", "ring", "--out", str(tmp_path / "t.zarr"),
          "--timeout", "-1"], "--timeout"),
        (["generate", "--catalogue", "1", "--classes", "box", "ring", "--out", str(tmp_path / "t.zarr"),
          "--timeout", "nan"], "--timeout"),
        (["generate", "--catalogue", "100000000", "--out", str(tmp_path / "c.zarr")], "VISUOTACTILE_MAX_OBJECTS"),
        (["generate", "--catalogue", "1", "--classes", "box", "ring", "--contours", "1000000000",
          "--out", str(tmp_path / "c.zarr")], "VISUOTACTILE_MAX_CONTOURS"),
        (["camera", "--source", "virtual:box", "--out", str(a_file / "sub")], "is a file, not a folder"),
        (["camera", "--source", "virtual:box", "--model", str(tmp_path / "missing.vtm")], "no such model file"),
        (["camera", "--source", "virtual:box", "--contours", "0"], "argument --contours: must be a positive integer"),
        (["camera", "--source", "virtual:box", "--strategy", "nowhere"], "unknown --strategy"),
        (["reproduce", "--data", str(tmp_path), "--out", str(a_file)], "is a file, not a folder"),
        (["reproduce", "--data", str(folder / "meshes"), "--out", str(tmp_path / "r"), "--classes", "Cup"],
         "at least two classes"),
    ]
    for argv, message in cases:
        one_line(capsys, 2, argv, message)
    assert not (tmp_path / "t.zarr").exists() and not (tmp_path / "c.zarr").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "folder"]  # nothing written, nothing half-made


def _box_off(x: float, y: float, z: float) -> str:
    corners = [(i * x, j * y, k * z) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    quads = ["4 0 2 3 1", "4 4 5 7 6", "4 0 1 5 4", "4 2 6 7 3", "4 0 4 6 2", "4 1 3 7 5"]
    return "OFF\n8 6 0\n" + "".join(f"{a} {b} {c}\n" for a, b, c in corners) + "\n".join(quads) + "\n"


def test_non_utf8_file_names_work(model, tmp_path, capsys):
    # Names made from file names that are not UTF-8 are printed, hashed and stored with \xNN escapes.
    root = os.fsencode(tmp_path)
    mesh = os.fsdecode(root + b"/cube\xfd.off")
    Path(mesh).write_text(_box_off(10, 10, 10))
    capsys.readouterr()
    assert main(["recognize", mesh, "--model", str(model), "--strategy", "blind", "--touches", "2"]) == 0
    assert capsys.readouterr().out.startswith("cube\\xfd: ")
    for cls, name, size in ((b"box\xff", b"a\xfe.off", (10, 10, 20)), (b"ring", b"b.off", (10, 20, 30))):
        os.makedirs(root + b"/meshes/" + cls)
        Path(os.fsdecode(root + b"/meshes/" + cls + b"/" + name)).write_text(_box_off(*size))
    out = tmp_path / "named.zarr"
    assert main(["generate", "--data", os.fsdecode(root + b"/meshes"), "--out", str(out), "--strategies", "blind",
                 "--contours", "2", "--probes", "4", "--workers", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["classes"] == ["box\\xff", "ring"]


def test_interrupted_train_does_not_promise_to_resume(store, tmp_path, capsys, monkeypatch):
    import fusion.training

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fusion.training, "train_on_store", interrupted)
    assert main(["train", "--store", str(store), "--model", "knn", "--out", str(tmp_path / "m.vtm")]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing was saved" in err[0] and "resume" not in err[0]
    monkeypatch.setattr("tactile.dataset.generate", interrupted)
    assert main(["generate", "--catalogue", "1", "--classes", "box", "ring", "--out", str(tmp_path / "g.zarr")]) == 130
    assert "re-run to resume" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------- racing and killed
def test_second_generate_on_a_store_being_written_is_refused(store, tmp_path, capsys):
    from tactile.dataset.store import store_lock

    out = tmp_path / "busy.zarr"
    with store_lock(out):  # another run holds the store
        one_line(capsys, 2, ["generate", "--catalogue", "1", "--classes", "box", "ring", "--out", str(out),
                             "--strategies", "blind", "--contours", "2", "--probes", "4"],
                 "another generate run", str(os.getpid()))
    assert not out.exists()


def test_folder_left_by_a_killed_creation_is_removed(tmp_path):
    from tactile.dataset.store import remove_stale_creations

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".s.zarr.creating-{dead.pid}"
    (stale / "frames").mkdir(parents=True)
    alive = tmp_path / f".s.zarr.creating-{os.getpid()}"  # this process: still creating, kept
    alive.mkdir()
    assert remove_stale_creations(tmp_path / "s.zarr") == [stale]
    assert not stale.exists() and alive.exists()


@pytest.mark.slow
def test_generate_killed_while_creating_leaves_nothing_that_blocks_a_rerun(tmp_path):
    # SIGKILL right after the temporary folder exists: the next run removes it and creates the store.
    out = tmp_path / "k.zarr"
    code = textwrap.dedent(f"""
        import os, signal
        import zarr
        original = zarr.open_group
        def open_then_die(path, *a, **k):
            group = original(path, *a, **k)
            if ".creating-" in str(path):
                os.kill(os.getpid(), signal.SIGKILL)
            return group
        zarr.open_group = open_then_die
        from tactile.dataset import generate
        from tactile.sensor import FSRSensor
        generate([("box", 0), ("ring", 0)], {str(out)!r}, strategies="blind", contours_per_object=2, probes=4,
                 sensor=FSRSensor(rows=4, cols=4), workers=1, progress=False)
    """)
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, timeout=120, check=False)
    assert done.returncode == -9, done.stderr[-2000:]
    assert [p.name for p in tmp_path.iterdir() if ".creating-" in p.name], "the kill did not land mid-creation"
    report = generate([("box", 0), ("ring", 0)], out, strategies="blind", contours_per_object=2, probes=4,
                      sensor=FSRSensor(rows=4, cols=4), workers=1, progress=False)
    assert report.completed == 2
    assert not [p for p in tmp_path.iterdir() if ".creating-" in p.name]


@pytest.mark.parametrize("argv", [["bench", "--help"], pytest.param(["verify", "STORE"], marks=pytest.mark.slow)])
def test_closed_output_pipe_is_one_line_and_exit_2(store, argv):
    argv = [str(store) if a == "STORE" else a for a in argv]
    child = subprocess.Popen([sys.executable, "-m", "fusion.cli", *argv], cwd=ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    child.stdout.close()  # `... | head -0`: the reader is gone before the first line
    err = child.stderr.read().decode().strip().splitlines()
    assert child.wait(timeout=120) == 2
    assert len(err) == 1 and "output pipe was closed" in err[0], err


# ------------------------------------------------------------------------------------------------ recordings
def _png(width: int, height: int, mode: str = "L") -> bytes:
    """A PNG whose header says ``width`` x ``height`` and whose pixel data is one compressed row: a few hundred
    bytes that would decode to a huge image."""
    color_type, depth, channels = {"L": (0, 8, 1), "RGB": (2, 8, 3), "I;16": (0, 16, 2)}[mode]

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, depth, color_type, 0, 0, 0)
    idat = zlib.compress(b"\0" * (1 + width * channels))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _recording(folder: Path, **changes) -> Path:
    from perception.camera import Intrinsics, RGBDFrame, write_recording

    color = np.full((24, 32, 3), 128, np.uint8)
    depth = np.full((24, 32), 500.0, np.float32)
    frame = RGBDFrame(color, depth, Intrinsics(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24), np.eye(4),
                      0.0, name="f")
    write_recording(folder, [frame])
    index = json.loads((folder / "recording.json").read_text())
    name = index["frames"][0]
    meta = json.loads((folder / f"{name}.json").read_text())
    for key, value in changes.items():
        if key in ("depth_scale", "frames"):
            index[key] = value
        elif key == "size":
            (folder / f"{name}.color.png").write_bytes(_png(*value, mode="RGB"))
            (folder / f"{name}.depth.png").write_bytes(_png(*value, mode="I;16"))
            meta.update(width=value[0], height=value[1])
        else:
            meta[key] = value
    (folder / "recording.json").write_text(json.dumps(index))
    (folder / f"{name}.json").write_text(json.dumps(meta))
    return folder


RECORDINGS = {
    "depth_scale text": ({"depth_scale": "mm"}, "'depth_scale' must be a finite positive number"),
    "depth_scale zero": ({"depth_scale": 0}, "'depth_scale' must be a finite positive number"),
    "timestamp text": ({"timestamp_s": "noon"}, "'timestamp_s' must be a finite number"),
    "pose text": ({"pose": "identity"}, "pose must be"),
    "pose ragged": ({"pose": [[1, 0], [0]]}, "pose must be"),
    "pose 3 x 3": ({"pose": np.eye(3).tolist()}, "pose must be a finite 4 x 4"),
    "frame outside the folder": ({"frames": ["../../etc/passwd"]}, "not a plain file name"),
    "frame absolute path": ({"frames": ["/etc/passwd"]}, "not a plain file name"),
    "9000 x 9000 images": ({"size": (9000, 9000)}, "VISUOTACTILE_MAX_IMAGE_PIXELS"),
    "16000 x 16000 images": ({"size": (16000, 16000)}, "VISUOTACTILE_MAX_IMAGE_PIXELS"),
}


@pytest.mark.parametrize("case", sorted(RECORDINGS))
def test_hostile_recordings_are_one_line_and_exit_2(tmp_path, capsys, case):
    changes, message = RECORDINGS[case]
    folder = _recording(tmp_path / "rec", **changes)
    one_line(capsys, 2, ["camera", "--source", str(folder), "--out", str(tmp_path / "out")], str(folder), message)


def test_pixel_limit_is_read_from_its_variable(tmp_path, capsys, monkeypatch):
    from perception.camera import read_recording

    folder = _recording(tmp_path / "rec")
    assert len(read_recording(folder)) == 1
    monkeypatch.setenv(LIMITS["image_pixels"].env, "100")
    with pytest.raises(Exception, match="32 x 24 pixels.*limit of 100"):
        read_recording(folder)
