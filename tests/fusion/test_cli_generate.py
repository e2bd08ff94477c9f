"""``visuotactile generate``: catalogue and folder sources, the summary, resume, refusals, exit codes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.cli import main
from tactile.dataset import open_dataset

CUBE_OFF = "OFF\n8 6 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n1 0 1\n1 1 1\n0 1 1\n" + "".join(
    f"4 {f}\n" for f in ("0 3 2 1", "4 5 6 7", "0 1 5 4", "1 2 6 5", "2 3 7 6", "3 0 4 7")
)
SMALL = ["--strategies", "blind", "--contours", "3", "--probes", "4", "--workers", "2", "--no-progress"]


def test_catalogue_generation_prints_a_json_summary_and_resumes(tmp_path, capsys):
    args = ["generate", "--catalogue", "1", "--classes", "box", "can", "--out", str(tmp_path / "s"), *SMALL]
    assert main([*args, "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["completed"] == 2 and result["stored_sequences"] == 6 and result["classes"] == ["box", "can"]
    assert result["bytes_per_sequence"] > 0 and result["failed"] == []
    ds = open_dataset(tmp_path / "s")
    assert ds.object_names == ("box/0", "can/0")
    assert ds.attrs["command"] == (
        f"visuotactile generate --catalogue 1 --classes box can --out {tmp_path / 's'} --strategies blind "
        "--contours 3 --probes 4 --seed 0"
    )
    # Same command again: nothing to do. Other settings: refused with exit 2 and one line.
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "2/2 complete (0 now, 2 already)" in out and "bytes/sequence" in out
    assert main([*args[:-1], "--seed", "1"]) == 2
    err = capsys.readouterr().err
    assert "other settings" in err and "seed: 0 in the store, 1 asked" in err and len(err.strip().splitlines()) == 1


def test_folder_generation_picks_classes_and_objects_per_class(tmp_path, capsys):
    for cls, names in (("cube", ("a", "b", "c")), ("other", ("d",))):
        (tmp_path / "data" / cls).mkdir(parents=True)
        for name in names:
            # a comment makes each file its own object (byte-identical meshes count as one)
            (tmp_path / "data" / cls / f"{name}.off").write_text(CUBE_OFF.replace("OFF\n", f"OFF\n# {name}\n", 1))
    (tmp_path / "data" / "cube" / "z_broken.off").write_text("OFF\n8 6 0\n0 0 0\n")
    out = tmp_path / "s"
    code = main(["generate", "--data", str(tmp_path / "data"), "--classes", "cube", "--objects-per-class", "2",
                 "--out", str(out), *SMALL])
    assert code == 0
    ds = open_dataset(out)
    assert ds.object_names == ("cube/a", "cube/b") and ds.class_names == ("cube",)
    np.testing.assert_array_equal(ds.labels, 0)
    # All of the class, the broken file included: recorded as failed, listed, exit code 1.
    code = main(["generate", "--data", str(tmp_path / "data"), "--classes", "cube", "--out", str(tmp_path / "t"),
                 *SMALL])
    assert code == 1
    assert "failed     cube/z_broken" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--catalogue", "1", "--classes", "teapot"], "unknown catalogue classes ['teapot']"),
        (["--catalogue", "0"], "argument --catalogue: must be a positive integer"),
        (["--data", "NOWHERE"], "not a folder"),
        (["--catalogue", "1", "--classes", "box", "--captures", "100000000"],
         "--captures 100000000: the objects with their captures: 100000001 is above the limit of 100000 objects"),
    ],
)
def test_bad_sources_exit_2_with_one_line(tmp_path, capsys, argv, message):
    assert main(["generate", *argv, "--out", str(tmp_path / "s"), *SMALL]) == 2
    assert message in capsys.readouterr().err


def test_folder_sources_are_the_librarys_objects(tmp_path, capsys):
    """The command takes its objects from fusion.experiments.data: byte-identical meshes count once, and a class
    with fewer meshes than asked is refused (exit 2, one line) instead of silently kept short."""
    (tmp_path / "data" / "cube").mkdir(parents=True)
    for name in ("a", "b"):
        (tmp_path / "data" / "cube" / f"{name}.off").write_text(CUBE_OFF)  # identical: one object
    assert main(["generate", "--data", str(tmp_path / "data"), "--objects-per-class", "2",
                 "--out", str(tmp_path / "s"), *SMALL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fewer than the 2 asked for" in err[0]


def test_a_source_is_required(capsys):
    assert main(["generate", "--out", "x"]) == 2
    assert "one of the arguments" in capsys.readouterr().err


def test_captures_join_their_objects(tmp_path, capsys):
    """--captures 1: each object and its virtual capture (named "<name>@capture", the same class), recorded in the
    command; the capture counts as made from the object's file, so a split by object keeps the two together."""
    for cls, names in (("cube", ("a", "b")), ("slab", ("c", "d"))):
        (tmp_path / "data" / cls).mkdir(parents=True)
        for name in names:
            text = CUBE_OFF.replace("OFF\n", f"OFF\n# {name}\n", 1)
            if cls == "slab":  # a box 0.4 high: another shape
                head, body = text.split("8 6 0\n")
                vertices, faces = body.split("\n")[:8], body.split("\n")[8:]
                vertices = [v[:-1] + "0.4" if v.endswith(" 1") else v for v in vertices]
                text = head + "8 6 0\n" + "\n".join(vertices + faces)
            (tmp_path / "data" / cls / f"{name}.off").write_text(text)
    out = tmp_path / "s"
    assert main(["generate", "--data", str(tmp_path / "data"), "--captures", "1", "--out", str(out), *SMALL]) == 0
    ds = open_dataset(out)
    assert ds.object_names == ("cube/a", "cube/b", "slab/c", "slab/d",
                               "cube/a@capture", "cube/b@capture", "slab/c@capture", "slab/d@capture")
    assert ds.object_labels.tolist() == [0, 0, 1, 1, 0, 0, 1, 1]
    assert "--captures 1 --out" in ds.attrs["command"]
    meshes = ds.mesh_ids()
    assert meshes[0] == meshes[4] and meshes[2] == meshes[6] and len(set(meshes.tolist())) == 4
    group = np.array([n.split("@")[0] for n in ds.object_names])[ds.object_ids]
    for seed in range(4):
        train, test = ds.split_by_object(0.5, seed=seed)
        assert not set(group[train]) & set(group[test]) and len(set(group[test])) == 2
