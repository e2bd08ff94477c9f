"""store.write_rows against zarr's own writer on layouts, rows and values of every kind: the same data (or the same
error) and, where it writes directly, the same chunk files."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ShardingCodec

from tactile.dataset import store as store_module
from tactile.dataset.store import COMPRESSOR, ZARR_WRITE, open_for_writing, write_rows

PER = 4  # rows per chunk file of the arrays made here
FRAME = (3, 2, 2)


def _blosc(**overrides):
    return BloscCodec(**{**COMPRESSOR, **overrides})


def _make(root: Path, name: str, shape, dtype, *, chunks, shards=None, compressors=None, serializer="auto") -> Path:
    path = root / "a.zarr"
    kwargs = {"shards": shards} if shards else {}
    zarr.open_group(path, mode="w").create_array(
        name, shape=shape, dtype=dtype, chunks=chunks, fill_value=0, serializer=serializer,
        compressors=compressors if compressors is not None else [_blosc(), Crc32cCodec()], **kwargs)
    return path


def _frames_store(root: Path, **kw) -> Path:
    kw.setdefault("shards", (PER, *FRAME))
    kw.setdefault("chunks", (1, *FRAME))
    return _make(root, "frames", (3 * PER, *FRAME), "uint16", **kw)


def _files(array_dir: Path) -> dict[str, bytes]:
    return {str(f.relative_to(array_dir)): f.read_bytes()
            for f in sorted(array_dir.rglob("*")) if f.is_file() and f.name != "zarr.json"}


def _outcome(path: Path, name: str, write):
    array = open_for_writing(path, name)
    try:
        write(array)
    except Exception as exc:  # noqa: BLE001 -- compared with what zarr raises
        return ("error", type(exc))
    return ("ok", zarr.open_array(f"{path}/{name}", mode="r")[...])


def _same_as_zarr(path: Path, name: str, rows, values, *, same_bytes: bool = True):
    """write_rows on ``path`` and zarr's ``array[rows] = values`` on a copy: same data (or the same error), and
    the same chunk files where the write succeeded."""
    other = Path(shutil.copytree(path, path.parent / "zarr-copy.zarr"))
    ours = _outcome(path, name, lambda a: write_rows(path, name, a, rows, values))

    def by_zarr(array):
        with zarr.config.set(ZARR_WRITE):
            array[rows] = values

    theirs = _outcome(other, name, by_zarr)
    assert ours[0] == theirs[0], (ours, theirs)
    if ours[0] == "error":
        assert issubclass(ours[1], theirs[1]) or issubclass(theirs[1], ours[1]), (ours, theirs)
        return
    assert ours[1].dtype == theirs[1].dtype
    assert np.array_equal(ours[1], theirs[1], equal_nan=ours[1].dtype.kind == "f")
    if same_bytes:
        assert _files(path / name) == _files(other / name)


def _codes(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 65536, (n, *FRAME)).astype(np.uint16)


# ------------------------------------------------------------------------------- layouts zarr must write
LAYOUTS = {
    "frames, big-endian rows": {"serializer": BytesCodec(endian="big")},
    "frames, other cname": {"compressors": [_blosc(cname="zstd"), Crc32cCodec()]},
    "frames, other clevel": {"compressors": [_blosc(clevel=1), Crc32cCodec()]},
    "frames, typesize 1": {"compressors": [_blosc(typesize=1), Crc32cCodec()]},
    "frames, fixed blocksize": {"compressors": [_blosc(blocksize=64), Crc32cCodec()]},
    "frames, inner chunks of 2 rows": {"chunks": (2, *FRAME)},
    "frames, shards split a frame": {"shards": (PER, 3, 2, 1), "chunks": (1, 3, 2, 1)},
    "frames, shards wider than a frame": {"shards": (PER, 3, 2, 4)},  # two inner chunks a row, one of them empty
}


@pytest.mark.parametrize("label", list(LAYOUTS))
def test_frames_of_another_layout_are_the_data_and_bytes_zarr_writes(tmp_path, label):
    path = _frames_store(tmp_path, **LAYOUTS[label])
    assert not store_module._direct_layout(open_for_writing(path, "frames"))
    _same_as_zarr(path, "frames", slice(0, 2 * PER), _codes(2 * PER))


@pytest.mark.parametrize("index", ["big-endian", "no checksum", "at the start"])
def test_a_shard_index_of_another_layout_is_written_by_zarr(tmp_path, index):
    # zarr's create_array takes only inner codecs; a ShardingCodec built by hand sets the index codecs/location.
    path = tmp_path / "a.zarr"
    index_codecs = {"big-endian": [BytesCodec(endian="big"), Crc32cCodec()], "no checksum": [BytesCodec()],
                    "at the start": [BytesCodec(), Crc32cCodec()]}[index]
    sharding = ShardingCodec(chunk_shape=(1, *FRAME), codecs=[BytesCodec(), _blosc(), Crc32cCodec()],
                             index_codecs=index_codecs, index_location="start" if index == "at the start" else "end")
    zarr.create_array(path, shape=(3 * PER, *FRAME), dtype="uint16", chunks=(PER, *FRAME), serializer=sharding,
                      compressors=None, fill_value=0)
    array = zarr.open_array(path, mode="r+").with_config({"write_empty_chunks": True})
    assert not store_module._direct_layout(array)
    other = Path(shutil.copytree(path, tmp_path / "zarr-copy.zarr"))
    codes = _codes(2 * PER, 1)
    write_rows(path.parent, path.name, array, slice(0, 2 * PER), codes)
    theirs = zarr.open_array(other, mode="r+").with_config({"write_empty_chunks": True})
    with zarr.config.set(ZARR_WRITE):
        theirs[: 2 * PER] = codes
    assert np.array_equal(zarr.open_array(path, mode="r")[: 2 * PER], codes)
    assert _files(path) == _files(other)


def test_an_unsharded_array_whose_chunks_split_rows_is_written_by_zarr(tmp_path):
    path = _make(tmp_path, "positions", (3 * PER, 3, 3), "float32", chunks=(PER, 3, 1))
    assert not store_module._direct_layout(open_for_writing(path, "positions"))
    values = np.random.default_rng(2).normal(0, 50, (2 * PER, 3, 3)).astype(np.float32)
    _same_as_zarr(path, "positions", slice(0, 2 * PER), values)


def test_a_big_endian_unsharded_array_reads_back_its_values(tmp_path):
    path = _make(tmp_path, "positions", (3 * PER, 3), "float64", chunks=(PER, 3), serializer=BytesCodec(endian="big"))
    values = np.random.default_rng(3).normal(0, 50, (PER, 3))
    _same_as_zarr(path, "positions", slice(PER, 2 * PER), values)


# ------------------------------------------------------------------------------- rows and values
@pytest.mark.parametrize("rows, n", [
    (slice(1, 1 + PER), PER),  # whole-file length, not aligned
    (slice(0, 2), 2),  # aligned, part of a file
    (slice(PER, PER + 2), 2),
    (slice(0, 2 * PER, 2), PER),  # stepped, the right number of values
    (slice(-PER, None), PER),  # negative bounds (whole last file)
    (slice(2 * PER, 5 * PER), PER),  # runs past the end: the last file only
])
def test_any_rows_give_the_data_zarr_writes(tmp_path, rows, n):
    path = _frames_store(tmp_path)
    open_for_writing(path, "frames")[:] = _codes(3 * PER, 9)  # rows that a misplaced write would change
    _same_as_zarr(path, "frames", rows, _codes(n, 4))


def test_values_that_do_not_fit_the_rows_fail_as_in_zarr(tmp_path):
    path = _frames_store(tmp_path)
    # A step of 2 over two files with a value per row of the range: zarr refuses (4 rows selected, 8 values).
    _same_as_zarr(path, "frames", slice(0, 2 * PER, 2), _codes(2 * PER, 5))


@pytest.mark.parametrize("values", ["scalar", "one frame", "one probe"])
def test_broadcast_values_give_the_data_zarr_writes(tmp_path, values):
    path = _frames_store(tmp_path)
    codes = _codes(PER, 6)
    value = {"scalar": np.uint16(7), "one frame": codes[0], "one probe": codes[:, :1]}[values]
    _same_as_zarr(path, "frames", slice(0, PER), value)


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # NaN to uint16: both casts warn
@pytest.mark.parametrize("kind", ["float64", "int64 out of range", "float NaN", "big-endian", "strided", "list"])
def test_values_of_another_dtype_or_layout_give_the_data_zarr_writes(tmp_path, kind):
    path = _frames_store(tmp_path)
    codes = _codes(2 * PER, 7)
    values = {
        "float64": codes.astype(np.float64) + 0.75,
        "int64 out of range": codes.astype(np.int64) * 3 - 70000,
        "float NaN": np.where(codes > 30000, np.nan, codes.astype(np.float64)),
        "big-endian": codes.astype(">u2"),
        "strided": np.ascontiguousarray(codes.swapaxes(1, 3)).swapaxes(1, 3),
        "list": codes.tolist(),
    }[kind]
    _same_as_zarr(path, "frames", slice(0, 2 * PER), values)


@pytest.mark.parametrize("dtype, kind", [("float32", "float64"), ("float32", "int64"), ("float64", "float32"),
                                         ("int64", "float64"), ("float32", ">f8")])
def test_rows_of_the_other_arrays_cast_as_zarr_does(tmp_path, dtype, kind):
    path = _make(tmp_path, "positions", (3 * PER, 3), dtype, chunks=(PER, 3))
    assert store_module._direct_layout(open_for_writing(path, "positions"))
    values = (np.random.default_rng(8).normal(0, 1e6, (2 * PER, 3))).astype(kind)
    _same_as_zarr(path, "positions", slice(PER, 3 * PER), values)


# ------------------------------------------------------------------------------- arrays zarr must handle
def test_rows_given_other_than_as_a_slice_go_through_zarr(tmp_path):
    _same_as_zarr(_frames_store(tmp_path / "int"), "frames", 0, _codes(1, 11)[0])
    _same_as_zarr(_frames_store(tmp_path / "all"), "frames", slice(None), _codes(3 * PER, 12))


def test_a_zarr_v2_array_is_written_by_zarr(tmp_path):
    path = tmp_path / "v2.zarr"
    zarr.open_group(path, mode="w", zarr_format=2).create_array("positions", shape=(2 * PER, 3, 3), dtype="float32",
                                                              chunks=(PER, 3, 3), fill_value=0)
    array = open_for_writing(path, "positions")
    assert not store_module._direct_layout(array)
    values = np.arange(2 * PER * 9, dtype=np.float32).reshape(2 * PER, 3, 3)
    write_rows(path, "positions", array, slice(0, 2 * PER), values)
    assert np.array_equal(zarr.open_array(f"{path}/positions", mode="r")[:], values)


def test_a_read_only_array_is_refused_as_zarr_refuses_it(tmp_path):
    path = _frames_store(tmp_path)
    before = _files(path / "frames")
    array = zarr.open_array(f"{path}/frames", mode="r")
    assert not store_module._direct_layout(array)
    with pytest.raises(ValueError, match="read.only"):
        write_rows(path, "frames", array, slice(0, PER), _codes(PER, 13))
    assert _files(path / "frames") == before


def test_an_array_that_skips_empty_chunks_is_written_by_zarr(tmp_path):
    path = _frames_store(tmp_path)
    array = zarr.open_array(f"{path}/frames", mode="r+")  # write_empty_chunks off: zarr leaves zero chunks out
    assert not store_module._direct_layout(array)
    codes = _codes(2 * PER, 14)
    codes[:PER] = 0
    write_rows(path, "frames", array, slice(0, 2 * PER), codes)
    other = _frames_store(tmp_path / "other")
    with zarr.config.set(ZARR_WRITE):
        zarr.open_array(f"{other}/frames", mode="r+")[: 2 * PER] = codes
    assert _files(path / "frames") == _files(other / "frames")
    assert np.array_equal(zarr.open_array(f"{path}/frames", mode="r")[: 2 * PER], codes)
