"""A reader reads rows in any order as zarr reads them: rows asked for in store order are decoded straight into what
is returned (``read_rows(out=...)``) and hashed where they lie, others through a sorted read and a copy; damage is
refused on either path."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from perception.errors import DatasetError, InvalidArgumentError
from tactile.dataset import open_dataset
from tactile.dataset.store import chunk_files, read_rows
from tests._small_store import SETTINGS

ROWS = SETTINGS["contours_per_object"]  # one strategy: an object's rows are one frames shard and one chunk
PER_SEQUENCE = ("normals", "positions", "tangents", "pad_sides_mm", "plane_points", "plane_normals")
INDICES = {
    "all": None,
    "in order": np.arange(2 * ROWS),
    "one object": np.arange(ROWS, 2 * ROWS),
    "reversed": np.arange(2 * ROWS)[::-1].copy(),
    "repeats": np.array([7, 1, 7, 0, 11, 6, 6, 2]),
    "an object shuffled, with repeats": np.array([5, 3, 0, 9, 4, 1, 2, 3, 0]),
    # a whole object's rows spanning one stretch of the output, but not in order: hashed in store order all the same
    "an object, two rows swapped": np.array([0, 2, 1, 3, 4, 5]),
    "sparse in order": np.array([0, 2, 3, 9, 10]),
    "one": np.array([5]),
    "none": np.zeros(0, dtype=np.int64),
}


def chunk_of(path: Path, name: str, obj: int) -> Path:
    (file,) = chunk_files(path, name, zarr.open_array(path / name, mode="r"), obj * ROWS, (obj + 1) * ROWS)
    return file


def flip(file: Path, at: int) -> None:
    data = bytearray(file.read_bytes())
    data[at] ^= 0xFF
    file.write_bytes(bytes(data))


@pytest.mark.parametrize("case", INDICES)
def test_load_reads_every_array_as_zarr_reads_it_in_any_order(store, case):
    index = INDICES[case]
    rows = np.arange(2 * ROWS) if index is None else index  # both objects complete: sequence i is store row i
    batch = open_dataset(store).load(index)
    settings = zarr.open_group(store, mode="r").attrs["visuotactile_dataset"]["settings"]
    codes = zarr.open_array(store / "frames", mode="r")[...][rows]
    frames = (codes.astype(np.float64) * settings["encoding"]["scale"]).astype(np.float32)
    assert batch.frames.dtype == np.float32 and batch.frames.tobytes() == frames.tobytes()
    for name in PER_SEQUENCE:
        expected = zarr.open_array(store / name, mode="r")[...][rows]
        got = getattr(batch, name)
        assert got.dtype == expected.dtype and got.shape == expected.shape and got.tobytes() == expected.tobytes(), name


@pytest.mark.parametrize("name", ["frames", "normals", "labels"])
def test_rows_decoded_into_a_given_array_are_those_zarr_reads(store, name):
    array = zarr.open_array(store / name, mode="r")
    whole = array[...]
    for lo, hi in ((0, ROWS), (ROWS, 2 * ROWS), (2, 5)):
        out = np.full((hi - lo, *array.shape[1:]), 7, dtype=array.dtype)
        assert read_rows(store, name, array, lo, hi, "x", out=out) is out
        assert out.tobytes() == whole[lo:hi].tobytes()
    for bad in (np.empty((ROWS + 1, *array.shape[1:]), array.dtype), np.empty((ROWS, *array.shape[1:]), np.float64),
                np.empty((2 * ROWS, *array.shape[1:]), array.dtype)[::2]):
        with pytest.raises(InvalidArgumentError, match="out must be"):
            read_rows(store, name, array, 0, ROWS, "x", out=bad)


@pytest.mark.parametrize("case", ["all", "one object", "reversed"])
@pytest.mark.parametrize("name", ["frames", "normals"])
def test_a_damaged_chunk_is_refused_whatever_the_order(copy, case, name):
    file = chunk_of(copy, name, 1)
    flip(file, file.stat().st_size // 2 if name == "frames" else file.stat().st_size - 6)
    index = INDICES[case]
    with pytest.raises(DatasetError, match=rf"'ring/0' is damaged: its {name} rows 6\.\.11 do not read back"):
        open_dataset(copy).load(index)
    assert open_dataset(copy).load(np.arange(ROWS)).frames.any()  # the other object still reads


@pytest.mark.parametrize("case", ["all", "in order", "reversed", "repeats"])
@pytest.mark.parametrize("name", ["frames", "normals"])
def test_a_chunk_copied_from_another_object_is_refused_by_the_row_checksums_whatever_the_order(copy, case, name):
    shutil.copyfile(chunk_of(copy, name, 1), chunk_of(copy, name, 0))  # its own checksums hold
    with pytest.raises(DatasetError, match=rf"'box/0' is damaged: its {name} row \d differs from the checksum"):
        open_dataset(copy).load(INDICES[case])


@pytest.mark.parametrize("case", ["all", "in order", "reversed", "an object shuffled, with repeats"])
def test_a_chunk_copied_from_another_object_is_refused_by_the_digest_whatever_the_order(copy, case):
    """Records without row checksums (written before they were kept): the whole-object digest is what tells."""
    for obj in (0, 1):
        file = copy / "records" / f"{obj:05d}.json"
        record = json.loads(file.read_text())
        del record["row_checksums"]
        file.write_text(json.dumps(record))
    shutil.copyfile(chunk_of(copy, "frames", 1), chunk_of(copy, "frames", 0))
    with pytest.raises(DatasetError, match=r"'box/0' is damaged: its frames rows differ from the digest"):
        open_dataset(copy).load(INDICES[case])
    assert open_dataset(copy).load(np.arange(ROWS, 2 * ROWS)).frames.any()


@pytest.mark.parametrize("inner, endian", [((1, 3, 2), "little"), ((1, 3, 4), "big")])
def test_rows_of_a_layout_left_to_zarr_land_in_the_given_array_too(tmp_path, inner, endian):
    """Inner chunks splitting a row, or big-endian values, are read by zarr: what it reads is copied into ``out``."""
    from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ShardingCodec

    from tactile.dataset import store as store_module

    values = np.arange(4 * 3 * 4, dtype=np.uint16).reshape(4, 3, 4) * 7
    codecs = [BytesCodec(endian=endian), BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"), Crc32cCodec()]
    sharding = ShardingCodec(chunk_shape=inner, codecs=codecs, index_codecs=[BytesCodec(endian="little"), Crc32cCodec()])
    zarr.create_array(tmp_path / "a", shape=values.shape, chunks=(2, 3, 4), dtype="uint16", serializer=sharding,
                      compressors=None, fill_value=0, config={"write_empty_chunks": True})[:] = values
    array = zarr.open_array(tmp_path / "a", mode="r")
    assert not store_module._chunk_plan(tmp_path, "a", array).direct
    for lo, hi in ((0, 2), (2, 4), (1, 2)):
        out = np.full((hi - lo, 3, 4), 9999, dtype=np.uint16)
        assert read_rows(tmp_path, "a", array, lo, hi, "x", out=out) is out
        np.testing.assert_array_equal(out, values[lo:hi])
