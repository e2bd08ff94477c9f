"""store.write_rows: the frames shards written without zarr's codec pipeline are the bytes zarr writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from tactile.dataset import open_dataset
from tactile.dataset import store as store_module
from tactile.dataset.store import ARRAYS, ZARR_WRITE, chunk_files, open_for_writing, write_rows


def _codes(shape, seed: int) -> np.ndarray:
    """Codes of mixed compressibility: smooth ramps, noise, a row of zeros and one of the largest code."""
    rng = np.random.default_rng(seed)
    codes = (np.arange(np.prod(shape[1:])).reshape(shape[1:]) * 37 % 4096).astype(np.uint16)[None].repeat(shape[0], 0)
    codes[1::2] = rng.integers(0, 65536, (len(codes[1::2]), *shape[1:]), dtype=np.uint16)
    codes[0] = 0
    codes[-1] = 65535
    return codes


def _file_bytes(path: Path, name: str, array, rows: slice) -> list[bytes]:
    return [f.read_bytes() for f in chunk_files(path, name, array, rows.start, rows.stop)]


def test_shard_files_are_the_bytes_zarr_writes(copy, tmp_path):
    import shutil

    other = Path(shutil.copytree(copy, tmp_path / "other.zarr"))
    mine, theirs = open_for_writing(copy, "frames"), open_for_writing(other, "frames")
    rows = slice(0, 2 * store_module.rows_per_file(mine))  # both objects' shards
    codes = _codes((rows.stop, *mine.shape[1:]), 0)
    write_rows(copy, "frames", mine, rows, codes)
    with zarr.config.set(ZARR_WRITE):
        theirs[rows] = codes
    ours, zarrs = _file_bytes(copy, "frames", mine, rows), _file_bytes(other, "frames", theirs, rows)
    assert len(ours) == 2 and ours == zarrs
    assert np.array_equal(zarr.open_array(f"{copy}/frames", mode="r")[rows], codes)


@pytest.mark.parametrize("name", [n for n in ARRAYS if n != "frames"])
def test_chunk_files_of_the_other_arrays_are_the_bytes_zarr_writes(copy, tmp_path, name):
    import shutil

    other = Path(shutil.copytree(copy, tmp_path / "other.zarr"))
    mine, theirs = open_for_writing(copy, name), open_for_writing(other, name)
    rows = slice(0, 2 * store_module.rows_per_file(mine))
    rng = np.random.default_rng(len(name))
    dtype = np.dtype(mine.dtype)
    if dtype.kind == "f":
        values = rng.normal(0, 50, (rows.stop, *mine.shape[1:])).astype(dtype)
        values.flat[0] = -0.0
    else:
        info = np.iinfo(dtype)
        values = rng.integers(info.min, info.max, (rows.stop, *mine.shape[1:]), dtype=dtype, endpoint=True)
    write_rows(copy, name, mine, rows, values)
    with zarr.config.set(ZARR_WRITE):
        theirs[rows] = values
    ours, zarrs = _file_bytes(copy, name, mine, rows), _file_bytes(other, name, theirs, rows)
    assert len(ours) == 2 and ours == zarrs
    assert np.array_equal(zarr.open_array(f"{copy}/{name}", mode="r")[rows], values)


def test_store_generated_through_it_reads_back(store):
    # The fixture's store was written by generate(), which writes frames through write_rows: zarr reads every
    # shard, and each row's CRC-32C matches its record (open_dataset checks them).
    data = open_dataset(store)
    frames = data.frames(np.arange(len(data)))
    assert frames.shape[0] == len(data) and np.isfinite(frames).all() and frames.max() > 0


def test_rows_that_are_not_whole_shards_go_through_zarr(copy, monkeypatch):
    array = open_for_writing(copy, "frames")
    codes = _codes((2, *array.shape[1:]), 1)
    monkeypatch.setattr(store_module, "atomic_path", lambda *a: pytest.fail("wrote a whole shard for 2 rows"))
    write_rows(copy, "frames", array, slice(1, 3), codes)
    assert np.array_equal(zarr.open_array(f"{copy}/frames", mode="r")[1:3], codes)


def test_another_layout_goes_through_zarr(tmp_path, monkeypatch):
    from zarr.codecs import BloscCodec, Crc32cCodec

    monkeypatch.setattr(store_module, "atomic_path", lambda *a: pytest.fail("wrote a shard zarr would encode otherwise"))
    for compressor in ({"cname": "zstd", "clevel": 1, "shuffle": "shuffle"},  # the stores written until 2026-11-27
                       {"cname": "lz4", "clevel": 5, "shuffle": "bitshuffle"}):
        path = tmp_path / f"{compressor['cname']}-{compressor['shuffle']}"
        group = zarr.open_group(path, mode="w")
        group.create_array("frames", shape=(4, 3, 2, 2), dtype="uint16", shards=(2, 3, 2, 2), chunks=(1, 3, 2, 2),
                           compressors=[BloscCodec(**compressor), Crc32cCodec()], fill_value=0)
        array = open_for_writing(path, "frames")
        assert not store_module._direct_layout(array)
        codes = _codes((4, 3, 2, 2), 2)
        write_rows(path, "frames", array, slice(0, 4), codes)
        assert np.array_equal(zarr.open_array(f"{path}/frames", mode="r")[:], codes)
    plain = tmp_path / "plain"  # an unsharded array whose chunks split the rows' trailing axes
    zarr.open_group(plain, mode="w").create_array(
        "positions", shape=(4, 3, 3), dtype="float32", chunks=(2, 3, 1),
        compressors=[BloscCodec(cname="zstd", clevel=1, shuffle="shuffle"), Crc32cCodec()], fill_value=0)
    array = open_for_writing(plain, "positions")
    assert not store_module._direct_layout(array)
    values = np.arange(36, dtype=np.float32).reshape(4, 3, 3)
    write_rows(plain, "positions", array, slice(0, 4), values)
    assert np.array_equal(zarr.open_array(f"{plain}/positions", mode="r")[:], values)


def test_every_array_of_a_store_is_written_directly(copy):
    assert all(store_module._direct_layout(open_for_writing(copy, name)) for name in ARRAYS)


def test_an_interrupted_write_leaves_the_old_shard_and_no_temporary_file(copy, monkeypatch):
    from numcodecs import Blosc

    array = open_for_writing(copy, "frames")
    per = store_module.rows_per_file(array)
    (shard,) = chunk_files(copy, "frames", array, 0, per)
    before = shard.read_bytes()
    calls = {"n": 0}
    encode = Blosc.encode

    def failing(self, buf):
        calls["n"] += 1
        if calls["n"] == per - 1:
            raise KeyboardInterrupt
        return encode(self, buf)

    monkeypatch.setattr(Blosc, "encode", failing)
    with pytest.raises(KeyboardInterrupt):
        write_rows(copy, "frames", array, slice(0, per), _codes((per, *array.shape[1:]), 3))
    assert calls["n"] == per - 1
    assert shard.read_bytes() == before
    assert sorted(p.name for p in shard.parent.iterdir()) == [shard.name]


def test_a_store_compressed_as_before_is_written_and_read_the_same(tmp_path, monkeypatch, store):
    # Arrays created with zstd (the stores written until 2026-11-27): the workers see another layout and write through
    # zarr, and the store reads the same values as the fixture's (LZ4) store; its chunk files are zstd frames.
    from tests._small_store import small_store

    monkeypatch.setattr(store_module, "COMPRESSOR", {"cname": "zstd", "clevel": 1, "shuffle": "shuffle"})
    old = small_store(tmp_path / "zstd.zarr")
    monkeypatch.undo()
    frames = open_for_writing(old, "frames")
    assert not store_module._direct_layout(frames)
    blosc_codec = frames.metadata.codecs[0].codecs[1]
    assert str(getattr(blosc_codec.cname, "value", blosc_codec.cname)) == "zstd"
    a, b = open_dataset(old), open_dataset(store)
    rows = np.arange(len(b))
    assert np.array_equal(a.frames(rows), b.frames(rows))
    assert np.array_equal(a.labels, b.labels)
