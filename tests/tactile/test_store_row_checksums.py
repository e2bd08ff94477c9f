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

from perception.errors import DatasetError
from tactile.dataset import open_dataset, verify_store
from tactile.dataset.store import (
    ROW_CHECKED_ARRAYS,
    SHARD_ENTRY_BYTES,
    chunk_files,
    decode_row_checksums,
    encode_row_checksums,
    row_checksums,
)
from tests._small_store import SETTINGS, small_store

ROWS = SETTINGS["contours_per_object"]  # one strategy: an object's rows are one frames shard


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return small_store(tmp_path_factory.mktemp("rowsums") / "store.zarr")


@pytest.fixture
def copy(store, tmp_path) -> Path:
    return Path(shutil.copytree(store, tmp_path / "copy.zarr"))


def shard(path: Path, obj: int) -> Path:
    array = zarr.open_array(f"{path}/frames", mode="r")
    (file,) = chunk_files(path, "frames", array, obj * ROWS, (obj + 1) * ROWS)
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
    with pytest.raises(DatasetError, match="object 'box/0' was written with other settings than the store's zarr.json"):
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
