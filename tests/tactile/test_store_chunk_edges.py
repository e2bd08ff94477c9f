"""Store chunk checks at their edges: a chunk file one byte above max_chunk_file_bytes is refused from its size; a
Blosc header whose compressed size is not the chunk's (CRC-32C valid) is refused undecoded; an oversized metadata
file zarr could read (.zattrs) is refused when the store is opened."""

from __future__ import annotations

from pathlib import Path

import google_crc32c
import numpy as np
import pytest
import zarr

from perception.errors import DatasetError
from tactile.dataset import open_dataset
from tactile.dataset.store import MAX_JSON_BYTES, max_chunk_file_bytes, read_rows

ROWS = 6  # rows per object in the small store


def normals_chunk(store: Path):
    array = zarr.open_array(store / "normals", mode="r")
    return array, store / "normals" / array.metadata.encode_chunk_key((0, *(0,) * (array.ndim - 1)))


def test_a_chunk_file_one_byte_above_its_bound_is_refused_from_its_size(copy):
    array, chunk = normals_chunk(copy)
    most = max_chunk_file_bytes(array)
    with open(chunk, "r+b") as f:
        f.truncate(most + 1)
    with pytest.raises(DatasetError, match=rf"is {most + 1} bytes, more than its rows can take \({most}\)"):
        read_rows(copy, "normals", array, 0, ROWS, "box/0")


def test_a_chunk_declaring_another_compressed_size_is_refused_undecoded(copy):
    array, chunk = normals_chunk(copy)
    body = bytearray(chunk.read_bytes()[:-4])
    cbytes = int.from_bytes(body[12:16], "little")
    assert cbytes == len(body)  # the layout the check reads
    body[12:16] = (cbytes + 4096).to_bytes(4, "little")  # Blosc 1 reads cbytes from the header: past the buffer
    chunk.write_bytes(bytes(body) + google_crc32c.value(bytes(body)).to_bytes(4, "little"))
    with pytest.raises(DatasetError, match=rf"declares a compressed size of {cbytes + 4096} bytes, but holds {cbytes}"):
        read_rows(copy, "normals", array, 0, ROWS, "box/0")


def test_an_oversized_zattrs_is_refused_when_the_store_is_opened(copy):
    with open(copy / ".zattrs", "wb") as f:
        f.truncate(MAX_JSON_BYTES + 1)  # sparse
    with pytest.raises(DatasetError, match=r"\.zattrs: \d+ bytes, more than the \d+ a store's metadata file may hold"):
        open_dataset(copy).load(np.arange(ROWS))


def test_a_folder_where_a_chunk_file_should_be_is_a_missing_chunk(copy):
    array, chunk = normals_chunk(copy)
    chunk.unlink()
    chunk.mkdir()
    with pytest.raises(DatasetError, match=r"its normals chunk \S+ is missing"):
        read_rows(copy, "normals", array, 0, ROWS, "box/0")


def test_a_shard_shorter_than_its_index_is_damage_zarr_names(copy):
    array = zarr.open_array(copy / "frames", mode="r")
    shard = copy / "frames" / array.metadata.encode_chunk_key((0, *(0,) * (array.ndim - 1)))
    shard.write_bytes(shard.read_bytes()[:50])
    with pytest.raises(DatasetError, match=r"'box/0' is damaged: its frames rows 0\.\.5 do not read back"):
        read_rows(copy, "frames", array, 0, ROWS, "box/0")


def test_a_store_with_far_more_files_than_its_settings_is_refused(copy):
    junk = copy / "junk"
    junk.mkdir()
    for k in range(4000):
        (junk / str(k)).touch()
    with pytest.raises(DatasetError, match=r"holds more than \d+ files and folders"):
        open_dataset(copy)


def test_a_symlinked_folder_inside_the_store_is_not_listed_again(copy):
    (copy / "records" / "loop").symlink_to(copy)  # inside the store: listed where it is, not followed
    assert len(open_dataset(copy).load(np.arange(ROWS)).frames) == ROWS


def test_the_chunk_file_bound_stays_near_the_rows_raw_bytes(store):
    """max_chunk_file_bytes is the rows' raw bytes plus a small overhead (Blosc, CRC-32C, shard index), not a
    multiple of them: a loose bound would let a large file be read whole before its checksum fails."""
    from tactile.dataset.store import ARRAYS, rows_per_file

    for name in ARRAYS:
        array = zarr.open_array(store / name, mode="r")
        raw = rows_per_file(array) * int(np.prod(array.shape[1:])) * array.dtype.itemsize
        assert raw < max_chunk_file_bytes(array) < raw + raw // 4 + 16 * 1024, name
