"""Where a chunk belongs: each record's row checksums catch a chunk moved from another object's rows, or marked
absent (read as zeros), in reads of some rows; its settings digest catches ``zarr.json`` settings edited after the
rows were written."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
import zarr

from fusion.cli import main
from perception.errors import DatasetError
from tactile.dataset import generate, open_dataset, verify_store
from tactile.dataset.store import (
    ROW_CHECKED_ARRAYS,
    SHARD_ENTRY_BYTES,
    chunk_files,
    decode_row_checksums,
    encode_row_checksums,
    row_checksums,
)
from tactile.sensor import FSRSensor
from tests._small_store import OBJECTS, SETTINGS

ROWS = SETTINGS["contours_per_object"]  # one strategy: an object's rows are one frames shard
OTHER = "it was written with other settings than the store's zarr.json now holds"


def shard(path: Path, obj: int) -> Path:
    array = zarr.open_array(f"{path}/frames", mode="r")
    (file,) = chunk_files(path, "frames", array, obj * ROWS, (obj + 1) * ROWS)
    return file


def edit_record(path: Path, obj: int, change) -> None:
    file = path / "records" / f"{obj:05d}.json"
    data = json.loads(file.read_text())
    change(data)
    file.write_text(json.dumps(data))


def frames_shard(path: Path, lo: int, hi: int) -> Path:
    (file,) = chunk_files(path, "frames", zarr.open_array(f"{path}/frames", mode="r"), lo, hi)
    return file


def mark_absent(file: Path, inner: int, n_inner: int) -> None:
    """Set inner chunk ``inner``'s shard index entry to absent, the index's CRC-32C made valid again."""
    data = bytearray(file.read_bytes())
    start = len(data) - (n_inner * SHARD_ENTRY_BYTES + 4)
    struct.pack_into("<QQ", data, start + inner * SHARD_ENTRY_BYTES, 2**64 - 1, 2**64 - 1)
    index = bytes(data[start:-4])
    data[-4:] = google_crc32c.value(index).to_bytes(4, "little")
    file.write_bytes(bytes(data))


# ------------------------------------------------------------------------------------------ the helpers
def test_row_checksums_are_crc32c_by_its_check_values():
    # RFC 3720 (iSCSI) B.4 and the CRC catalogue's check value.
    rows = np.zeros((2, 32), np.uint8)
    rows[1, :9] = np.frombuffer(b"123456789", np.uint8)
    assert row_checksums(rows[:1], np.uint8).tolist() == [0x8A9136AA]
    assert row_checksums(rows[1:, :9], np.uint8).tolist() == [0xE3069283]
    # As the array's dtype, C order: a float64 row is checked as its float32 bytes when the array is float32.
    values = np.array([[1.5, -2.0]])
    assert row_checksums(values, np.float32)[0] == google_crc32c.value(np.float32([1.5, -2.0]).tobytes())


def test_row_checksums_round_trip_through_record_text_and_malformed_text_is_refused():
    sums = np.array([0, 1, 2**32 - 1, 0xE3069283], np.uint32)
    assert np.array_equal(decode_row_checksums(encode_row_checksums(sums), 4, "here"), sums)
    for bad in (encode_row_checksums(sums[:3]), encode_row_checksums(sums)[:-4] + "!!!!", 17, None, "",
                encode_row_checksums(np.zeros(5, np.uint32))):
        with pytest.raises(DatasetError, match="here: malformed row checksums"):
            decode_row_checksums(bad, 4, "here")


# --------------------------------------------------------------------------------------- the records
def test_each_record_holds_the_checksum_of_every_row_of_the_arrays_read_in_parts(store):
    for obj in range(2):
        record = json.loads((store / "records" / f"{obj:05d}.json").read_text())
        assert sorted(record["row_checksums"]) == sorted(ROW_CHECKED_ARRAYS)
        for name in ROW_CHECKED_ARRAYS:
            rows = zarr.open_array(f"{store}/{name}", mode="r")[obj * ROWS:(obj + 1) * ROWS]
            direct = [google_crc32c.value(np.ascontiguousarray(r).tobytes()) for r in rows]
            assert decode_row_checksums(record["row_checksums"][name], ROWS, name).tolist() == direct


def test_a_shard_swapped_for_another_objects_is_caught_by_reads_of_single_sequences(copy):
    shutil.copyfile(shard(copy, 0), shard(copy, 1))
    ds = open_dataset(copy)
    ring = np.flatnonzero(ds.object_ids == 1)
    with pytest.raises(DatasetError, match="object 'ring/0' is damaged: its frames row 0 differs from the checksum"):
        ds.frames(ring[:1])
    items = ds.torch_dataset(ring)
    with pytest.raises(DatasetError, match="object 'ring/0' is damaged: its frames row differs from the checksum"):
        items[0]
    box = ds.torch_dataset(np.flatnonzero(ds.object_ids == 0))
    assert np.array_equal(box[2][0].numpy(), ds.frames([2])[0])  # the intact object reads as before
    assert verify_store(copy).damaged == {"ring/0": "its frames rows differ from the digest in its record"}


def test_an_inner_chunk_marked_absent_reads_as_damage_not_as_zeros(copy):
    mark_absent(shard(copy, 1), inner=2, n_inner=ROWS)
    assert not zarr.open_array(f"{copy}/frames", mode="r")[ROWS + 2].any()  # what zarr alone reads: zeros
    ds = open_dataset(copy)
    with pytest.raises(DatasetError, match="object 'ring/0' is damaged: its frames row 2 differs from the checksum"):
        ds.frames([ROWS + 2])
    with pytest.raises(DatasetError, match="'ring/0' is damaged: its frames row differs from the checksum"):
        ds.torch_dataset([ROWS + 2])[0]
    ds.frames([ROWS + 1, ROWS + 3])  # its neighbours are intact
    assert verify_store(copy).damaged == {"ring/0": "its frames rows differ from the digest in its record"}


def test_settings_edited_after_the_rows_were_written_are_refused(copy):
    meta = json.loads((copy / "zarr.json").read_text())
    encoding = meta["attributes"]["visuotactile_dataset"]["settings"]["encoding"]
    encoding["scale"] *= 2  # still a valid scale: every frame would read twice as far
    (copy / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="object 'box/0' was written with other settings than the store's zarr.json"
                                           r".* as was every object \(2\): the metadata was edited; regenerate the store"):
        open_dataset(copy)
    assert verify_store(copy).damaged == {
        name: "it was written with other settings than the store's zarr.json now holds" for name in ("box/0", "ring/0")}


def test_damaged_row_checksums_in_a_record_are_damage_of_that_object(copy):
    record = copy / "records" / "00001.json"
    data = json.loads(record.read_text())
    sums = decode_row_checksums(data["row_checksums"]["positions"], ROWS, "positions")
    data["row_checksums"]["positions"] = encode_row_checksums(sums ^ np.uint32(1))
    record.write_text(json.dumps(data))
    ds = open_dataset(copy)
    ds.load(np.flatnonzero(ds.object_ids == 0))  # the other object reads
    with pytest.raises(DatasetError, match="'ring/0' is damaged: its positions row 0 differs from the checksum"):
        ds.load([ROWS])
    assert verify_store(copy).damaged == {"ring/0": "its record's row checksums of positions are not those of its rows"}
    data["row_checksums"]["positions"] = "not base64!"
    record.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="object 'ring/0': its record's positions: malformed row checksums"):
        open_dataset(copy).load([ROWS])
    del data["row_checksums"]["positions"]
    record.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="object 'ring/0': its record has no row checksums of positions"):
        open_dataset(copy).load([ROWS])
    assert verify_store(copy).damaged == {"ring/0": "its record's row checksums of positions are not those of its rows"}


# ------------------------------------------------------------------------------- the settings digest
@pytest.mark.parametrize("written", ["0" * 64, 5, ["x"], {"a": 1}, None], ids=["other hex", "int", "list", "dict",
                                                                                "null"])
def test_a_later_record_alone_holding_another_settings_digest_is_refused(copy, written):
    # Only the second object's record differs: a check of the first record alone passes (mutation survived).
    edit_record(copy, 1, lambda d: d.__setitem__("settings_sha256", written))
    with pytest.raises(DatasetError, match="object 'ring/0' was written with other settings"):
        open_dataset(copy)
    assert verify_store(copy).damaged == {"ring/0": OTHER}


def test_one_record_with_another_settings_digest_is_named_as_damage_and_generate_repairs_it(copy):
    edit_record(copy, 1, lambda d: d.__setitem__("settings_sha256", "0" * 64))
    with pytest.raises(DatasetError, match="object 'ring/0' was written with other settings.* as were 0 of the 1 other "
                                           "complete objects: their records are damaged.*re-running `visuotactile "
                                           "generate` with the store's settings explores them again"):
        open_dataset(copy)
    report = generate(OBJECTS, copy, **SETTINGS)  # the remedy the message gives
    assert report.repaired == [("ring/0", OTHER)] and report.completed == 1
    assert open_dataset(copy).object_names == ("box/0", "ring/0")


def test_settings_holding_nan_are_never_a_foreign_exception(copy, capsys):
    # json.loads reads NaN in zarr.json (a key the settings check does not know): an edit, refused as one (the digest
    # once raised ValueError there, a traceback on the command line).
    meta = json.loads((copy / "zarr.json").read_text())
    meta["attributes"]["visuotactile_dataset"]["settings"]["encoding"]["note"] = float("nan")
    (copy / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="object 'box/0' was written with other settings"):
        open_dataset(copy)
    assert verify_store(copy).damaged == {"box/0": OTHER, "ring/0": OTHER}
    assert main(["verify", str(copy)]) == 1  # damage found: verify's exit status, no traceback
    assert "2 damaged" in capsys.readouterr().out


# --------------------------------------------------------------------------------- malformed records
@pytest.mark.parametrize("sums", [[1, 2], "abc", 0, None], ids=["list", "str", "int", "null"])
def test_row_checksums_that_are_not_a_mapping_are_damage_of_that_object(copy, sums):
    edit_record(copy, 1, lambda d: d.__setitem__("row_checksums", sums))
    ds = open_dataset(copy)
    ds.load([0, 1])  # the other object reads
    with pytest.raises(DatasetError, match="object 'ring/0': its record has no row checksums of"):
        ds.load([ROWS + 1])
    with pytest.raises(DatasetError, match="object 'ring/0': its record has no row checksums of frames"):
        ds.frames([ROWS + 1])
    assert "ring/0" in verify_store(copy).damaged and len(verify_store(copy).damaged) == 1


def test_text_of_the_right_length_with_other_padding_is_malformed_not_a_value_error():
    # 4 checksums: 16 bytes, 24 characters ending "==". 24 characters without padding decode to 18 bytes.
    with pytest.raises(DatasetError, match="here: malformed row checksums"):
        decode_row_checksums("A" * 24, 4, "here")


# ---------------------------------------------------------------------- old and new records together
def test_a_read_across_an_old_record_and_a_new_one_checks_the_new_ones_rows(copy):
    # Object 0's record predates row checksums (a store resumed after the upgrade); object 1's rows are object 0's.
    edit_record(copy, 0, lambda d: (d.pop("row_checksums"), d.pop("settings_sha256")))
    shutil.copyfile(frames_shard(copy, 0, ROWS), frames_shard(copy, ROWS, 2 * ROWS))
    ds = open_dataset(copy)
    mixed = np.array([1, ROWS + 2])
    with pytest.raises(DatasetError, match="object 'ring/0' is damaged: its frames row 2 differs from the checksum"):
        ds.frames(mixed)
    items = ds.torch_dataset(mixed)
    assert np.array_equal(items[0][0].numpy(), ds.frames([1])[0])  # the old record's row: no checksum, reads
    with pytest.raises(DatasetError, match="'ring/0' is damaged: its frames row differs from the checksum"):
        items[1]


# ---------------------------------------------------------------- an object spanning several chunk files
@pytest.fixture(scope="module")
def two_strategies(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("two") / "store.zarr"
    generate([("box", 0), ("ring", 0)], path, strategies=("blind", "guided"), contours_per_object=3,
             sensor=FSRSensor(rows=4, cols=4), probes=4, seed=0, workers=1, progress=False)
    return path


def test_records_of_several_strategies_hold_each_rows_checksum_in_row_order(two_strategies, tmp_path):
    block = 6
    for obj in range(2):
        record = json.loads((two_strategies / "records" / f"{obj:05d}.json").read_text())
        for name in ROW_CHECKED_ARRAYS:
            rows = zarr.open_array(f"{two_strategies}/{name}", mode="r")[obj * block:(obj + 1) * block]
            direct = [google_crc32c.value(np.ascontiguousarray(r).tobytes()) for r in rows]
            assert decode_row_checksums(record["row_checksums"][name], block, name).tolist() == direct, name
    assert verify_store(two_strategies).ok
    copy = Path(shutil.copytree(two_strategies, tmp_path / "copy.zarr"))
    # The object's guided shard replaced by its own blind one: each passes its checksum, rows 3..5 are misplaced.
    shutil.copyfile(frames_shard(copy, block, block + 3), frames_shard(copy, block + 3, 2 * block))
    ds = open_dataset(copy)
    with pytest.raises(DatasetError, match="object 'ring/0' is damaged: its frames row 4 differs from the checksum"):
        ds.frames([block + 4])
    ds.frames([block + 1])  # its blind rows are intact
    assert verify_store(copy).damaged == {"ring/0": "its frames rows differ from the digest in its record"}


# ------------------------------------------------------------------------ every array read in parts
@pytest.mark.parametrize("name", ["normals", "positions", "tangents", "pad_sides_mm", "plane_points", "plane_normals"])
def test_a_chunk_of_any_array_read_in_parts_moved_from_another_object_is_caught_by_a_partial_read(copy, name):
    # Named here, not taken from ROW_CHECKED_ARRAYS: an array dropped from it goes unchecked (mutation survived).
    array = zarr.open_array(f"{copy}/{name}", mode="r")
    (src,) = chunk_files(copy, name, array, 0, ROWS)
    (dst,) = chunk_files(copy, name, array, ROWS, 2 * ROWS)
    k = int(np.flatnonzero((array[:ROWS] != array[ROWS:2 * ROWS]).reshape(ROWS, -1).any(axis=1))[0])
    shutil.copyfile(src, dst)  # row k is the first whose bytes change (a few of pad_sides_mm's are alike)
    ds = open_dataset(copy)
    with pytest.raises(DatasetError, match=f"object 'ring/0' is damaged: its {name} row {k} differs from the checksum"):
        ds.load([ROWS + k])


def test_settings_keys_reordered_in_zarr_json_are_not_an_edit(copy):
    meta = json.loads((copy / "zarr.json").read_text())
    settings = meta["attributes"]["visuotactile_dataset"]["settings"]
    meta["attributes"]["visuotactile_dataset"]["settings"] = dict(reversed(list(settings.items())))
    (copy / "zarr.json").write_text(json.dumps(meta))
    open_dataset(copy).load([ROWS + 1])
    assert verify_store(copy).ok
