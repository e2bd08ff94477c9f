"""Hostile stores whose checksums and digests are consistent (forged): a record's interest points that are not
(K, 3) finite points, an array rewritten in zarr's v2 format, and per-probe or per-plane rows holding NaN, Inf or
absurd magnitudes are refused with a DatasetError naming the store and the object (and verify lists the object as
damaged), never a raw exception or NaN handed on to the classifiers."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from perception.errors import DatasetError
from perception.geometry import ObjectModel
from perception.shapes import make_object
from tactile.dataset import generate, open_dataset, verify_store
from tactile.dataset.integrity import damaged_objects
from tactile.dataset.store import (
    MAX_INTEREST_POINTS,
    MAX_PAD_SIDE_MM,
    MAX_POSITION_MM,
    encode_row_checksums,
    open_for_writing,
    row_checksums,
    write_rows,
)
from tactile.sensor import MAX_LENGTH_MM, FSRSensor
from tests._small_store import OBJECTS, SETTINGS
from tests.tactile.test_dataset import store_files

ROWS = SETTINGS["contours_per_object"]  # one strategy: an object's rows are one chunk of each array
ISS = {"strategies": ("iss",), "contours_per_object": 2, "probes": 6, "sensor": FSRSensor(rows=8, cols=8), "seed": 0,
       "workers": 1, "progress": False}


def forge(path: Path, obj: int, name: str, change) -> None:
    """Rewrite object ``obj``'s rows of array ``name`` with ``change(rows)`` and make its record agree: the digest
    (SHA-256 of the rows' bytes) and the row checksums, as a forger with the format's documentation would."""
    array = open_for_writing(path, name)
    rows = slice(obj * ROWS, (obj + 1) * ROWS)
    values = np.ascontiguousarray(change(np.array(array[rows])), dtype=array.dtype)
    write_rows(path, name, array, rows, values)
    file = path / "records" / f"{obj:05d}.json"
    record = json.loads(file.read_text())
    record["digests"][name] = hashlib.sha256(values.tobytes()).hexdigest()
    record["row_checksums"][name] = encode_row_checksums(row_checksums(values, values.dtype))
    file.write_text(json.dumps(record))


def set_at(index, value):
    def change(values):
        values[index] = value
        return values
    return change


# ------------------------------------------------------------------------------------ A: interest points
@pytest.fixture(scope="module")
def iss_store(tmp_path_factory) -> Path:
    """One box explored by the ISS strategy: its record holds 10 interest points."""
    path = tmp_path_factory.mktemp("iss") / "iss.zarr"
    generate([("box", 0)], path, **ISS)
    return path


@pytest.fixture
def iss_copy(iss_store, tmp_path) -> Path:
    return Path(shutil.copytree(iss_store, tmp_path / "iss.zarr"))


def write_interest_points(path: Path, text: str) -> None:
    """Put ``text`` (JSON, written as is: NaN and 1e309 are what a hand edit can hold) as box/0's interest points."""
    file = path / "records" / "00000.json"
    record = json.loads(file.read_text())
    record["interest_points"] = "@@"
    file.write_text(json.dumps(record).replace('"@@"', text))


MAPPING = "interest points are not a mapping of strategy to points"
ISS_POINTS = "interest points of 'iss'"
BAD_POINTS = {  # what the record holds (JSON text) -> what the error says (a pattern)
    "a list": ("[1, 2]", rf"{MAPPING} \(got list\)"),
    "null": ("null", rf"{MAPPING} \(got NoneType\)"),
    "text": ('{"iss": "abc"}', rf"{ISS_POINTS} are not a list of \[x, y, z\] points \(got str\)"),
    "flat": ('{"iss": [1, 2, 3, 4]}', rf"{ISS_POINTS} are not \(K, 3\) points \(got shape \(4,\)\)"),
    "nested": ('{"iss": [[[1, 2, 3]]]}', rf"{ISS_POINTS} are not \(K, 3\) points \(got shape \(1, 1, 3\)\)"),
    "ragged": ('{"iss": [[1, 2, 3], [1, 2]]}',
               rf"{ISS_POINTS} are not a list of \[x, y, z\] points \(rows of different lengths\)"),
    "strings": ('{"iss": [["1", "2", "3"]]}', rf'{ISS_POINTS} are not numbers \(point 0 is \["1", "2", "3"\]\)'),
    "NaN": ('{"iss": [[0, 0, 0], [NaN, 0, 0]]}', f"{ISS_POINTS}: point 1 holds a non-finite coordinate"),
    "1e309": ('{"iss": [[1e309, 0, 0]]}', f"{ISS_POINTS}: point 0 holds a non-finite coordinate"),
    "far": ('{"iss": [[0, -2e6, 0]]}',
            rf"{ISS_POINTS}: point 0 holds a coordinate of -2e\+06 mm, beyond the \+-1e\+06 mm"),
    "other strategy": ('{"guided": [[1, 2, 3]]}',
                       (r"interest points name strategy 'guided', which the store does not have \(its strategies: "
                       r"\['iss'\]\)")),
    "too many": ('{"iss": [' + ", ".join(["[0, 0, 0]"] * (MAX_INTEREST_POINTS + 1)) + "]}",
                 f"{ISS_POINTS} hold {MAX_INTEREST_POINTS + 1} points, more than the {MAX_INTEREST_POINTS}"),
}


@pytest.mark.parametrize("case", BAD_POINTS, ids=list(BAD_POINTS))
def test_malformed_interest_points_are_refused_naming_the_store_the_object_and_the_record(iss_copy, case):
    text, problem = BAD_POINTS[case]
    write_interest_points(iss_copy, text)
    ds = open_dataset(iss_copy)  # the rows are intact: the store opens and loads
    assert len(ds.load()) == 2
    problem = f"its record records/00000.json: {problem}"
    with pytest.raises(DatasetError, match=f"^{re.escape(str(iss_copy))}: object 'box/0' is damaged: {problem}"):
        ds.interest_points("box/0")
    report = verify_store(iss_copy)
    assert list(report.damaged) == ["box/0"]
    assert re.fullmatch(problem + ".*", report.damaged["box/0"]), report.damaged
    assert damaged_objects(iss_copy) == {0: report.damaged["box/0"]}  # what generate re-explores


def test_interest_points_edited_to_other_finite_points_read_back_as_written(iss_copy):
    # The record's points are not under a digest: any finite (K, 3) points within the bound are what it says.
    write_interest_points(iss_copy, '{"iss": [[1.5, -2, 3], [0, 999999, -1e-300]]}')
    points = open_dataset(iss_copy).interest_points("box/0")
    assert list(points) == ["iss"]
    np.testing.assert_array_equal(points["iss"], [[1.5, -2.0, 3.0], [0.0, 999999.0, -1e-300]])
    assert points["iss"].dtype == np.float64
    write_interest_points(iss_copy, '{"iss": []}')
    assert open_dataset(iss_copy).interest_points("box/0")["iss"].shape == (0, 3)
    assert verify_store(iss_copy).ok


def test_the_generated_interest_points_are_ten_finite_points_within_the_object(iss_store):
    points = open_dataset(iss_store).interest_points("box/0")["iss"]
    assert points.shape == (10, 3) and np.isfinite(points).all() and np.abs(points).max() < 150.0
    assert verify_store(iss_store).ok


# ----------------------------------------------------------------------------------- B: zarr v2 arrays
def make_v2(path: Path, name: str = "normals") -> None:
    """Replace array ``name``'s zarr v3 metadata with a plausible zarr v2 ``.zarray`` of the same shape."""
    meta = json.loads((path / name / "zarr.json").read_text())
    (path / name / "zarr.json").unlink()
    (path / name / ".zarray").write_text(json.dumps({
        "zarr_format": 2, "shape": meta["shape"], "chunks": meta["chunk_grid"]["configuration"]["chunk_shape"],
        "dtype": "<f4", "compressor": None, "fill_value": 0, "order": "C", "filters": None}))


def test_a_zarr_v2_array_in_a_store_is_refused_by_verify_resume_and_reading_naming_it(copy, capsys):
    make_v2(copy)
    named = rf"^{re.escape(str(copy))}: the 'normals' array is "
    with pytest.raises(DatasetError, match=named):
        verify_store(copy)
    with pytest.raises(DatasetError, match=named):
        damaged_objects(copy)
    with pytest.raises(DatasetError, match=named):
        generate(OBJECTS, copy, **SETTINGS)  # resuming checks the store first
    with pytest.raises(DatasetError, match=f"^{re.escape(str(copy))}: .*'normals' array"):
        open_dataset(copy)
    assert main(["verify", str(copy), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'normals' array" in err[0] and "AttributeError" not in err[0]


def test_the_chunk_reader_refuses_a_v2_array_itself(copy):
    # read_rows is public: called with a v2 array (no codecs in its metadata) it names the array, as for other codecs.
    import zarr

    from tactile.dataset.store import read_rows

    make_v2(copy)
    array = zarr.open_array(f"{copy}/normals", mode="r")
    with pytest.raises(DatasetError, match=f"^{re.escape(str(copy))}: the 'normals' array is zarr format 2"):
        read_rows(copy, "normals", array, 0, ROWS, "box/0")


# ------------------------------------------------------------------------ C: values of the per-row arrays
NAN, INF = float("nan"), float("inf")
BEYOND = r"mm, beyond the \+-1e\+06 mm a store holds"
NOT_UNIT = "not a unit vector"
BAD_VALUES = {  # array, how its rows of ring/0 are forged -> what the error says (a pattern)
    "plane_normals NaN": ("plane_normals", set_at(np.s_[:], NAN), (r"its plane_normals row 0 holds a non-finite "
                          r"value \(nan\)")),
    "plane_points Inf": ("plane_points", set_at(np.s_[2, 1], INF), (r"its plane_points row 2 holds a non-finite "
                         r"value \(inf\)")),
    "plane_points far": ("plane_points", set_at(np.s_[3], 3e6), rf"its plane_points row 3 holds 3e\+06 {BEYOND}"),
    "plane_normals long": ("plane_normals", lambda v: v * 2, (f"its plane_normals row 0 holds a vector of length 2, "
                           f"{NOT_UNIT}")),
    "positions 3e38": ("positions", set_at(np.s_[:], 3e38), rf"its positions row 0 holds 3e\+38 {BEYOND}"),
    "positions -Inf": ("positions", set_at(np.s_[5, 2, 0], -INF), (r"its positions row 5 holds a non-finite value "
                       r"\(-inf\)")),
    "positions x1e30": ("positions", lambda v: v * np.float32(1e30), (rf"its positions row 0 holds -?\d\.?\d*e\+31 "
                        rf"{BEYOND}")),
    "normals one NaN": ("normals", set_at(np.s_[1, 4, 2], NAN), r"its normals row 1 holds a non-finite value \(nan\)"),
    "normals 3e38": ("normals", set_at(np.s_[:], 3e38), (rf"its normals row 0 holds a vector of length 5.2e\+38, "
                     f"{NOT_UNIT}")),
    "normals zero": ("normals", lambda v: np.zeros_like(v), f"its normals row 0 holds a vector of length 0, {NOT_UNIT}"),
    "tangents zero": ("tangents", set_at(np.s_[4, 0], 0.0), (f"its tangents row 4 holds a vector of length 0, "
                      f"{NOT_UNIT}")),
    "pad sides zero": ("pad_sides_mm", lambda v: np.zeros_like(v), (r"its pad_sides_mm row 0 holds a pad side of 0 mm, "
                       r"outside \(0, 10000\] mm")),
    "pad sides negative": ("pad_sides_mm", lambda v: -v, r"its pad_sides_mm row 0 holds a pad side of -20 mm"),
    "pad sides NaN": ("pad_sides_mm", set_at(np.s_[2, 3], NAN), r"its pad_sides_mm row 2 holds a non-finite value"),
}


@pytest.mark.parametrize("case", BAD_VALUES, ids=list(BAD_VALUES))
def test_forged_rows_out_of_bounds_are_refused_naming_the_store_the_object_and_the_array(copy, case):
    name, change, problem = BAD_VALUES[case]
    forge(copy, 1, name, change)  # ring/0; its checksums and digest agree with the forged rows
    ds = open_dataset(copy)
    box = np.flatnonzero(ds.object_ids == 0)
    assert np.isfinite(ds.load(box).positions).all()  # the other object reads
    message = f"^{re.escape(str(copy))}: object 'ring/0' is damaged: {problem}"
    with pytest.raises(DatasetError, match=message):
        ds.load()
    with pytest.raises(DatasetError, match=message):
        ds.load([0, *range(2 * ROWS - 1, ROWS - 1, -1)])  # rows in any order: the lowest one out of bounds is named
    row = int(re.match(r"its \w+ row (\d+)", problem)[1])
    with pytest.raises(DatasetError, match=message):
        ds.load([ROWS + row])  # a single sequence (no digest is checked: its row checksum agrees)
    if name != "plane_points" and name != "plane_normals":  # the arrays a torch Dataset carries
        with pytest.raises(DatasetError, match=message):
            ds.torch_dataset()
    report = verify_store(copy)
    assert list(report.damaged) == ["ring/0"]  # verify says the same of it, and generate re-explores it
    assert re.fullmatch(problem + ".*", report.damaged["ring/0"]), report.damaged


def test_rows_on_the_bounds_read_back_as_stored(copy):
    # Positions of 999,999 mm, normals of length 1 +- 1e-4 and a pad side of 10 m are within the bounds: read as stored.
    forge(copy, 1, "positions", set_at(np.s_[0, 0], [999_999.0, -999_999.0, 0.0]))
    forge(copy, 1, "normals", lambda v: v * np.float32(1.0001))
    forge(copy, 1, "pad_sides_mm", set_at(np.s_[0, 0], 1e4))
    batch = open_dataset(copy).load()
    np.testing.assert_array_equal(batch.positions[ROWS, 0], [999_999.0, -999_999.0, 0.0])
    assert batch.pad_sides_mm[ROWS, 0] == np.float32(1e4)
    np.testing.assert_allclose(np.linalg.norm(batch.normals, axis=-1)[ROWS:], 1.0001, rtol=1e-5)
    assert verify_store(copy).ok


def test_the_bounds_are_the_sensors_and_far_beyond_generated_objects(store):
    assert MAX_PAD_SIDE_MM == MAX_LENGTH_MM  # no sensor spec allows a larger pad
    batch = open_dataset(store).load()
    assert np.abs(batch.positions).max() < 150.0 < MAX_POSITION_MM  # objects are 150 mm across by default
    np.testing.assert_allclose(np.linalg.norm(batch.plane_normals, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(batch.normals, axis=-1), 1.0, atol=1e-6)


def test_generate_re_explores_an_object_with_forged_rows_and_ends_byte_identical(store, copy):
    forge(copy, 0, "plane_normals", set_at(np.s_[:], NAN))
    report = generate(OBJECTS, copy, **SETTINGS)
    assert [name for name, _ in report.repaired] == ["box/0"] and report.completed == 1
    assert store_files(copy) == store_files(store)
    assert verify_store(copy).ok


@pytest.mark.parametrize(("name", "value"), [("labels", 0), ("object_ids", 0), ("strategies", 3)])
def test_forged_identity_rows_are_damage_to_verify_as_to_a_reader_and_generate_repairs_them(store, copy, name, value):
    # ring/0 (object 1, class 'ring' = 1, one strategy) relabelled 'box' (or renumbered): the reader refused it, but
    # verify said intact, so generate never re-explored it and the store stayed unreadable.
    forge(copy, 1, name, lambda v: np.full_like(v, value))
    expected = {"labels": 1, "object_ids": 1, "strategies": 0}[name]
    with pytest.raises(DatasetError, match=f"object 'ring/0': its stored {name} \\({value}\\) contradict"):
        open_dataset(copy)
    assert verify_store(copy).damaged == {"ring/0": f"its stored {name} ({value}) contradict the store's settings "
                                                    f"({expected})"}
    report = generate(OBJECTS, copy, **SETTINGS)
    assert [n for n, _ in report.repaired] == ["ring/0"]
    assert store_files(copy) == store_files(store)


def far_box() -> ObjectModel:
    """A box 2 km from the origin: a model the geometry accepts (within 1e12 mm), beyond what a store holds."""
    box = make_object("box", 0)
    return ObjectModel(box.vertices + 2e6, box.triangles, name="far")


def test_generate_records_an_object_beyond_the_bounds_as_failed_not_a_store_it_then_refuses(tmp_path):
    from tactile.dataset.objects import ObjectSpec

    out = tmp_path / "far.zarr"
    specs = [ObjectSpec("far/0", "box", loader=far_box), ObjectSpec("box/0", "box", catalogue=("box", 0))]
    report = generate(specs, out, **SETTINGS)
    assert [name for name, _ in report.failed] == ["far/0"] and report.completed == 1
    assert "positions row 0 holds 2e+06 mm, beyond the +-1e+06 mm" in report.failed[0][1]
    ds = open_dataset(out)
    assert ds.object_names == ("box/0",) and verify_store(out).ok
    assert np.isfinite(ds.load().positions).all()


def test_a_store_with_no_complete_object_shows_no_verify_bar(tmp_path, capsys):
    """Nothing to verify (a store just created): no empty "verify: 0 objects" bar before the generation's own."""
    from perception import runtime
    from tactile.dataset.store import create_store
    from tests.test_atomic_writers import _store_settings

    create_store(tmp_path / "new.zarr", _store_settings(), {"command": "test"})
    runtime.set_progress(True)
    try:
        assert damaged_objects(tmp_path / "new.zarr", progress=True) == {}
    finally:
        runtime.set_progress(None)
    assert "verify" not in capsys.readouterr().err
