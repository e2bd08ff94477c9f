"""Stores that detect damage: per-chunk checksums, per-object digests, verify, and generate repairing exactly the
damaged objects to the bytes of an undamaged run."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from fusion.cli import main
from perception.errors import DatasetError
from tactile.dataset import generate, open_dataset, verify_store
from tactile.dataset.store import ARRAYS
from tactile.sensor import FSRSensor
from tests.tactile.test_dataset import store_files

OBJECTS = [("box", 0), ("can", 0), ("box", 1)]
SETTINGS = {"strategies": ("blind",), "contours_per_object": 6, "sensor": FSRSensor(rows=8, cols=8), "probes": 8,
            "seed": 1, "progress": False, "workers": 2}
ROWS = 6  # rows per object (one strategy x 6 contours): one frames shard and one chunk of each other array


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("integrity") / "store.zarr"
    generate(OBJECTS, path, **SETTINGS)
    return path


@pytest.fixture
def copy(store, tmp_path) -> Path:
    return Path(shutil.copytree(store, tmp_path / "copy.zarr"))


def chunk(path: Path, name: str, obj: int) -> Path:
    """The chunk file of object ``obj``'s rows of array ``name`` (a shard for frames)."""
    tail = {"frames": "/0/0/0", "normals": "/0/0", "positions": "/0/0", "tangents": "/0/0", "pad_sides_mm": "/0",
            "plane_points": "/0", "plane_normals": "/0"}.get(name, "")  # chunk keys: c/<row chunk>/0 per other axis
    return path / name / "c" / f"{obj}{tail}"


def flip(file: Path, offset: int = 12) -> None:
    data = bytearray(file.read_bytes())
    data[offset] ^= 0x01
    file.write_bytes(bytes(data))


def arrays_of(path: Path) -> dict[str, np.ndarray]:
    return {name: zarr.open_array(f"{path}/{name}", mode="r")[:] for name in ARRAYS}


# --------------------------------------------------------------------------------------------- intact
def test_every_chunk_has_a_checksum_and_every_record_the_digests_of_its_rows(store):
    for name in ARRAYS:
        codecs = json.loads((store / name / "zarr.json").read_text())["codecs"]
        inner = codecs[0]["configuration"]["codecs"] if codecs[0]["name"] == "sharding_indexed" else codecs
        assert inner[-1]["name"] == "crc32c", name  # on each chunk, not only on the shard index
    values = arrays_of(store)
    for obj in range(len(OBJECTS)):
        record = json.loads((store / "records" / f"{obj:05d}.json").read_text())
        for name in ARRAYS:
            rows = np.ascontiguousarray(values[name][obj * ROWS:(obj + 1) * ROWS])
            assert record["digests"][name] == hashlib.sha256(rows.tobytes()).hexdigest(), name
        # Chunks holding only zeros are written too (object 0's labels, ids and strategies are all 0).
        assert chunk(store, "labels", obj).stat().st_size > 0
    report = verify_store(store)
    assert report.ok and report.checked == 3 and not report.damaged and not report.incomplete


# ------------------------------------------------------------------------------------------- damage
DAMAGE = {
    "frames shard deleted": (lambda p: chunk(p, "frames", 1).unlink(), 1, "frames chunk frames/c/1/0/0/0 is missing"),
    "frames shard emptied": (lambda p: chunk(p, "frames", 1).write_bytes(b""), 1, "is missing"),
    "byte flipped in a frames chunk": (lambda p: flip(chunk(p, "frames", 2)), 2, "frames rows 12..17 do not read"),
    "frames shard truncated": (lambda p: chunk(p, "frames", 0).write_bytes(chunk(p, "frames", 0).read_bytes()[:-9]),
                               0, "frames rows 0..5 do not read"),
    "normals chunk deleted": (lambda p: chunk(p, "normals", 2).unlink(), 2, "normals chunk normals/c/2/0/0 is missing"),
    "byte flipped in a normals chunk": (lambda p: flip(chunk(p, "normals", 0)), 0, "normals rows 0..5"),
    "byte flipped in a labels chunk": (lambda p: flip(chunk(p, "labels", 1), 8), 1, "labels"),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_reading_a_damaged_object_raises_naming_it(copy, case, capsys):
    damage, obj, message = DAMAGE[case]
    name = "/".join(map(str, OBJECTS[obj]))
    damage(copy)
    report = verify_store(copy)
    assert list(report.damaged) == [name] and message in report.damaged[name]
    with pytest.raises(DatasetError, match=f"object '{name}' is damaged: .*{message}"):
        ds = open_dataset(copy)  # seeds, labels, ids and strategies are read (and checked) at open
        ds.load()
    if case.startswith("frames") or "frames chunk" in case:
        ds = open_dataset(copy)
        intact = np.flatnonzero(ds.object_ids != obj)
        np.testing.assert_array_equal(ds.load(intact).frames, open_dataset(copy).frames(intact))
        with pytest.raises(DatasetError, match=f"object '{name}' is damaged"):
            ds.frames(np.flatnonzero(ds.object_ids == obj)[:1])
        with pytest.raises(DatasetError, match=f"object '{name}' is damaged"):
            ds.torch_dataset(np.flatnonzero(ds.object_ids == obj))[0]
    assert main(["verify", str(copy), "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert f"damaged  {name}: " in out and "1 damaged" in out


def test_a_chunk_swapped_for_another_objects_passes_its_checksum_but_not_the_records(copy):
    shutil.copyfile(chunk(copy, "normals", 0), chunk(copy, "normals", 1))
    ds = open_dataset(copy)
    # The chunk is self-consistent; its record's row checksums tell, for whole objects and for parts of one alike.
    for index in (None, np.flatnonzero(ds.object_ids == 1)[:3]):
        with pytest.raises(DatasetError, match="object 'can/0' is damaged: its normals row 0 differs from the checksum"):
            ds.load(index)
    assert verify_store(copy).damaged == {"can/0": "its normals rows differ from the digest in its record"}
    # A record written before records held row checksums: whole objects are still checked against the digests.
    record = copy / "records" / "00001.json"
    old = json.loads(record.read_text())
    del old["row_checksums"], old["settings_sha256"]
    record.write_text(json.dumps(old))
    ds = open_dataset(copy)
    with pytest.raises(DatasetError, match="object 'can/0' is damaged: its normals rows differ from the digest"):
        ds.load()
    assert verify_store(copy).damaged == {"can/0": "its normals rows differ from the digest in its record"}


def test_unreadable_records_and_other_formats(copy, tmp_path, capsys):
    (copy / "records" / "00002.json").write_text("{ not json")
    report = verify_store(copy)
    assert report.damaged == {"box/1": "its completion record is unreadable"} and report.checked == 2
    meta = json.loads((copy / "zarr.json").read_text())
    meta["attributes"]["visuotactile_dataset"]["format"] = 1
    (copy / "zarr.json").write_text(json.dumps(meta))
    for call in (lambda: open_dataset(copy), lambda: verify_store(copy), lambda: generate(OBJECTS, copy, **SETTINGS)):
        with pytest.raises(DatasetError, match="format 1, made before stores carried checksums.*regenerate"):
            call()
    assert main(["verify", str(tmp_path / "nothing.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.zarr: no such dataset store" in err[0]


def test_a_damaged_store_never_evaluates(store, copy, tmp_path, capsys):
    from fusion.conventional import ConventionalClassifier

    model = ConventionalClassifier(kind="knn", som_iterations=200, n_select=10).fit(open_dataset(store).load())
    path = model.save(tmp_path / "knn.vtm")
    assert main(["evaluate", "--model", str(path), "--store", str(store), "--json"]) == 0
    capsys.readouterr()
    chunk(copy, "frames", 1).unlink()
    assert main(["evaluate", "--model", str(path), "--store", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "object 'can/0' is damaged" in err[0]


# ------------------------------------------------------------------------------------------- repair
def test_generate_re_explores_exactly_the_damaged_objects_and_ends_byte_identical(store, copy):
    chunk(copy, "frames", 0).unlink()  # a shard deleted
    flip(chunk(copy, "positions", 2))  # a chunk damaged
    (copy / "records" / "00001.json").unlink()  # and one object never finished
    report = generate(OBJECTS, copy, **SETTINGS)
    assert sorted(name for name, _ in report.repaired) == ["box/0", "box/1"]
    assert report.completed == 3 and report.skipped == 0 and not report.failed
    assert verify_store(copy).ok
    original, repaired = arrays_of(store), arrays_of(copy)
    for name in ARRAYS:
        assert repaired[name].tobytes() == original[name].tobytes(), name
    assert store_files(copy) == store_files(store)  # every chunk file, byte for byte, and the same records
    again = generate(OBJECTS, copy, **SETTINGS)  # intact now: nothing to do
    assert again.skipped == 3 and again.completed == 0 and not again.repaired
