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
    assert report.same == ["can/0"] and not report.ok  # an object not explored again is not verified
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


# --- added in review: what the tests above left free (each kills a mutation that survived them) -------------------

def _edited(store: Path, folder: Path, settings_edit=None, record_edit=None) -> Path:
    """A copy of ``store`` with its settings and/or records edited by hand (the checksums made to agree)."""
    copy = Path(shutil.copytree(store, folder))
    meta = json.loads((copy / "zarr.json").read_text())
    settings = meta["attributes"][ATTRS_KEY]["settings"]
    if settings_edit:
        settings_edit(settings)
        (copy / "zarr.json").write_text(json.dumps(meta))
    for file in sorted((copy / "records").glob("*.json")):
        content = json.loads(file.read_text())
        content["settings_sha256"] = settings_digest(settings)
        if record_edit:
            record_edit(content)
        file.write_text(json.dumps(content))
    return copy


def test_every_array_that_a_forged_seed_changes_is_named(store, tmp_path):
    forged = _edited(store, tmp_path / "forged.zarr", settings_edit=lambda s: s.update(seed=7))
    # every array drawn from the seed; the planes pass through the object's centre whatever the seed, and the
    # interest points are drawn with saliency seed 0
    drawn = "contour_seeds, frames, noise_seeds, normals, pad_sides_mm, plane_normals, positions, tangents"
    assert rerun_objects(forged, 3).differ == {"box/0": drawn, "mug/1": drawn, "can/2": drawn}


def test_edited_interest_points_differ(store, tmp_path):
    def shift(record):
        points = record["interest_points"]["guided"]
        points[0][0] += 1.0

    edited = _edited(store, tmp_path / "points.zarr", record_edit=shift)
    report = rerun_objects(edited, 3)
    assert set(report.differ.values()) == {"interest points"}


@pytest.mark.parametrize("digests", [None, ["x"], "abc", 3])
def test_a_record_with_malformed_digests_differs_and_does_not_crash(store, tmp_path, digests):
    edited = _edited(store, tmp_path / "digests.zarr", record_edit=lambda r: r.update(digests=digests))
    report = rerun_objects(edited, 1)
    assert len(report.differ) == 1 and "frames" in next(iter(report.differ.values()))


@pytest.mark.parametrize("catalogue", ["ab", ["box", float("inf")], ["box", float("nan")], ["box", -1], ["box", 1.0],
                                       ["box"], None, {"box": 0}, ["zzz", 0]])
def test_a_malformed_catalogue_entry_is_skipped_saying_why(store, tmp_path, catalogue):
    def edit(settings):
        settings["objects"][0]["catalogue"] = catalogue
        settings["objects"][1]["rotation_seed"] = -1  # refused by ObjectSpec

    report = rerun_objects(_edited(store, tmp_path / "cat.zarr", settings_edit=edit), 3)
    assert report.same == ["can/2"] and sorted(report.skipped) == ["box/0", "mug/1"]
    assert "malformed" in report.skipped["box/0"] or "unknown object class" in report.skipped["box/0"]
    assert "malformed" in report.skipped["mug/1"] and "rotation_seed" in report.skipped["mug/1"]


def test_objects_that_are_not_complete_are_not_drawn(store, tmp_path):
    copy = Path(shutil.copytree(store, tmp_path / "partial.zarr"))
    record = json.loads((copy / "records" / "00001.json").read_text())
    (copy / "records" / "00001.json").write_text(json.dumps(record | {"status": "failed"}))
    (copy / "records" / "00002.json").unlink()
    assert rerun_objects(copy, 5).same == ["box/0"]


def test_the_temporary_store_is_removed_on_every_path(store, tmp_path, monkeypatch):
    import tempfile

    import tactile.dataset.rerun as rerun_module

    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    rerun_objects(store, 1)
    assert not any(folder.iterdir())

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rerun_module, "explore_into_store", interrupted)
    with pytest.raises(KeyboardInterrupt):
        rerun_objects(store, 1)
    assert not any(folder.iterdir())


def test_the_cli_passes_seed_and_data(store, tmp_path, capsys):
    seeds = {seed: rerun_objects(store, 1, seed=seed).same for seed in range(6)}
    seed = next(s for s, same in seeds.items() if same != seeds[0])
    assert main(["verify", str(store), "--rerun", "1", "--seed", str(seed), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rerun"]["same"] == seeds[seed]
    assert main(["verify", str(store), "--rerun", "1", "--data", str(tmp_path / "none")]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_a_store_whose_objects_all_skip_is_not_verified(store, tmp_path, capsys):
    """Seed forged together with the digests, and every entry made a loader (or a mesh nowhere): nothing can be
    explored again, which must not read as verified."""
    def forge(settings):
        settings["seed"] = 7
        for entry in settings["objects"]:
            del entry["catalogue"]
            entry["loader"] = "perception.shapes.make_object"

    forged = _edited(store, tmp_path / "skipped.zarr", settings_edit=forge)
    assert verify_store(forged).ok
    assert main(["verify", str(forged), "--rerun", "3"]) == 1
    assert "skipped  " in capsys.readouterr().out


def test_bad_sensor_settings_name_the_store(store, tmp_path):
    from perception.errors import DatasetError

    edited = _edited(store, tmp_path / "sensor.zarr", settings_edit=lambda s: s["sensor"].update(range_mm=-1.0))
    with pytest.raises(DatasetError, match=r"sensor\.zarr/zarr\.json: malformed store settings: sensor"):
        rerun_objects(edited, 1)


@pytest.mark.parametrize("data", [b"/tmp", 3])
def test_a_data_that_is_not_a_path_is_refused(store, data):
    with pytest.raises(InvalidArgumentError, match="data must be a folder path"):
        rerun_objects(store, 1, data=data)


def test_the_cli_refuses_seed_or_data_without_rerun_and_its_json_ok_is_the_verdict(store, tmp_path, capsys):
    for extra in (["--seed", "3"], ["--data", str(tmp_path)]):
        assert main(["verify", str(store), *extra]) == 2
        assert "give --rerun N" in capsys.readouterr().err
    forged = _edited(store, tmp_path / "forged.zarr", settings_edit=lambda s: s.update(seed=7))
    assert main(["verify", str(forged), "--rerun", "1", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is False and out["rerun"]["ok"] is False and out["damaged"] == {}
