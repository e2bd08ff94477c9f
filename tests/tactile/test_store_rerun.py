"""Exploring a store's objects again from its settings (``rerun_objects``, ``visuotactile verify --rerun``): the
same bytes for a real store; differences for one whose seed was forged together with its digests (which
``verify_store`` cannot see); loader objects never called; meshes found where the store was moved."""

from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path

import open3d as o3d
import pytest

from fusion.cli import main
from perception.errors import InvalidArgumentError
from perception.shapes import make_object
from tactile.dataset import ObjectSpec, generate, rerun_objects, verify_store
from tactile.dataset.store import ATTRS_KEY, settings_digest
from tactile.sensor import FSRSensor

SETTINGS = {"strategies": ("guided", "blind"), "contours_per_object": 3, "sensor": FSRSensor(rows=8, cols=8),
            "probes": 5, "seed": 0, "progress": False, "workers": 1}


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rerun") / "store.zarr"
    generate([("box", 0), ("mug", 1), ("can", 2)], path, **SETTINGS)
    return path


def test_a_real_store_is_explored_again_to_the_same_bytes(store, capsys):
    report = rerun_objects(store, 5)
    assert report.ok and report.same == ["box/0", "mug/1", "can/2"] and not report.differ and not report.skipped
    assert len(rerun_objects(store, 1, seed=3).same) == 1
    assert main(["verify", str(store), "--rerun", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] and out["rerun"]["ok"] and len(out["rerun"]["same"]) == 2


def test_a_forged_seed_passes_the_checksums_but_not_a_rerun(store, tmp_path, capsys):
    forged = Path(shutil.copytree(store, tmp_path / "forged.zarr"))
    meta = json.loads((forged / "zarr.json").read_text())
    settings = meta["attributes"][ATTRS_KEY]["settings"]
    settings["seed"] = 7  # the rows stay those of seed 0; every digest that covers the settings is made to agree
    (forged / "zarr.json").write_text(json.dumps(meta))
    for record in (forged / "records").glob("*.json"):
        content = json.loads(record.read_text())
        content["settings_sha256"] = settings_digest(settings)
        record.write_text(json.dumps(content))
    assert verify_store(forged).ok  # what the checksums alone cannot tell
    report = rerun_objects(forged, 3)
    assert not report.ok and sorted(report.differ) == ["box/0", "can/2", "mug/1"]
    # the seeds and everything drawn from them differ; the labels, object ids and strategies do not
    for arrays in report.differ.values():
        names = set(arrays.split(", "))
        assert {"frames", "contour_seeds", "noise_seeds", "plane_normals"} <= names
        assert not names & {"labels", "object_ids", "strategies"}
    assert main(["verify", str(forged), "--rerun", "1"]) == 1
    assert "differs  " in capsys.readouterr().out


def test_loader_objects_are_never_called_from_a_store(tmp_path):
    path = tmp_path / "loader.zarr"
    spec = ObjectSpec("box/loaded", "box", loader=functools.partial(make_object, "box", 0))
    generate([spec, ("can", 0)], path, **SETTINGS)
    report = rerun_objects(path, 2)
    assert report.same == ["can/0"]
    assert list(report.skipped) == ["box/loaded"] and "loader function" in report.skipped["box/loaded"]
    assert "perception.shapes.make_object" in report.skipped["box/loaded"]


def test_meshes_are_found_in_a_moved_folder(tmp_path):
    folder = tmp_path / "meshes" / "Box"
    folder.mkdir(parents=True)
    box = make_object("box", 0)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(box.vertices.copy()),
                                     o3d.utility.Vector3iVector(box.triangles.copy()))
    assert o3d.io.write_triangle_mesh(str(folder / "b.off"), mesh)
    path = tmp_path / "files.zarr"
    generate([(folder / "b.off", "Box")], path, **SETTINGS)
    moved = tmp_path / "elsewhere"
    shutil.move(tmp_path / "meshes", moved)
    report = rerun_objects(path, 1)
    (name,) = report.skipped
    assert "is not found" in report.skipped[name] and not report.same
    assert rerun_objects(path, 1, data=moved).same == [name]


@pytest.mark.parametrize("kwargs, message", [({"objects": 0}, "objects must be an integer >= 1"),
                                             ({"objects": True}, "objects must be an integer >= 1"),
                                             ({"seed": -1}, "seed must be a non-negative integer"),
                                             ({"data": "/no/such/folder"}, "is not a folder")])
def test_bad_arguments_are_refused(store, kwargs, message):
    with pytest.raises(InvalidArgumentError, match=message):
        rerun_objects(store, **{"objects": 1, **kwargs})
