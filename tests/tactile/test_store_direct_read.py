"""Reading a store's chunks without zarr's per-chunk pipeline (``store._decode_rows``): the same values as zarr reads,
absent inner chunks as the fill value as zarr reads them, and every chunk or shard index whose checksum fails, or
whose Blosc frame does not decode, or whose index entries lie outside the chunk data, refused as damage naming the
object; layouts it does not decode go to zarr. Several tests come from a break attempt (2026-11-28)."""

from __future__ import annotations

import hashlib
import struct
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
import zarr

from perception.errors import DatasetError
from tactile.dataset import store as store_module
from tactile.dataset.store import ARRAYS, SHARD_ENTRY_BYTES, chunk_files, read_rows, update_digest

ROWS = 6  # rows per object in the small store (tests/_small_store.py)
INDEX_BYTES = ROWS * SHARD_ENTRY_BYTES + 4


def file_of(path: Path, name: str, obj: int) -> Path:
    (file,) = chunk_files(path, name, zarr.open_array(path / name, mode="r"), obj * ROWS, (obj + 1) * ROWS)
    return file


def entries(shard: Path) -> list[tuple[int, int]]:
    data = shard.read_bytes()
    return [tuple(e) for e in np.frombuffer(data[-INDEX_BYTES:-4], dtype="<u8").reshape(ROWS, 2).tolist()]


def flip(file: Path, at: int) -> None:
    data = bytearray(file.read_bytes())
    data[at] ^= 0xFF
    file.write_bytes(bytes(data))


def read(path: Path, name: str, lo: int = 0, hi: int = ROWS, owner: str = "box/0") -> np.ndarray:
    return read_rows(path, name, zarr.open_array(path / name, mode="r"), lo, hi, owner)


def zarr_read(path: Path, name: str, lo: int = 0, hi: int = ROWS) -> np.ndarray:
    return zarr.open_array(path / name, mode="r")[lo:hi]


@pytest.fixture
def no_zarr_reads(monkeypatch):
    """zarr's own reads of an array raise: what is read must be decoded here."""

    def refuse(self, selection):
        raise AssertionError(f"zarr read {self.path}[{selection}]")

    monkeypatch.setattr(zarr.Array, "__getitem__", refuse)


def test_every_array_of_a_generated_store_is_decoded_here_bit_for_bit(store, monkeypatch):
    expected = {name: zarr_read(store, name, 0, 2 * ROWS) for name in ARRAYS}
    arrays = {name: zarr.open_array(store / name, mode="r") for name in ARRAYS}

    def refuse(self, selection):
        raise AssertionError("zarr read")

    monkeypatch.setattr(zarr.Array, "__getitem__", refuse)
    for name in ARRAYS:
        for lo, hi in ((0, ROWS), (ROWS, 2 * ROWS), (2, 5), (ROWS + 5, 2 * ROWS)):
            got = read_rows(store, name, arrays[name], lo, hi, "x")
            assert got.dtype == expected[name].dtype and got.shape == expected[name][lo:hi].shape
            assert got.tobytes() == expected[name][lo:hi].tobytes(), (name, lo, hi)


def test_an_inner_chunk_marked_absent_reads_as_zarr_reads_it(copy):
    shard = file_of(copy, "frames", 1)
    data = bytearray(shard.read_bytes())
    struct.pack_into("<QQ", data, len(data) - INDEX_BYTES + 3 * SHARD_ENTRY_BYTES, 2**64 - 1, 2**64 - 1)
    data[-4:] = google_crc32c.value(bytes(data[-INDEX_BYTES:-4])).to_bytes(4, "little")
    shard.write_bytes(bytes(data))
    by_zarr = zarr_read(copy, "frames", ROWS, 2 * ROWS)
    assert not by_zarr[3].any() and by_zarr[2].any()  # zarr: the fill value (0) for the absent one only
    here = read(copy, "frames", ROWS, 2 * ROWS, "ring/0")
    np.testing.assert_array_equal(here, by_zarr)
    np.testing.assert_array_equal(read(copy, "frames", ROWS + 3, ROWS + 4, "ring/0"), by_zarr[3:4])


def test_a_shard_of_absent_chunks_only_reads_as_zeros_from_its_index(copy):
    shard = file_of(copy, "frames", 0)
    index = np.full(ROWS * 2, 2**64 - 1, dtype="<u8").tobytes()
    shard.write_bytes(b"\0" * 64 + index + google_crc32c.value(index).to_bytes(4, "little"))
    np.testing.assert_array_equal(read(copy, "frames"), zarr_read(copy, "frames"))
    assert not read(copy, "frames").any()


@pytest.mark.parametrize("row", [0, 4])
def test_a_byte_changed_in_an_inner_chunk_is_damage_naming_its_checksum(copy, row, no_zarr_reads):
    shard = file_of(copy, "frames", 0)
    offset, length = entries(shard)[row]
    flip(shard, offset + length // 2)
    message = rf"'box/0' is damaged: its frames rows 0\.\.5 do not read back \(inner chunk {row}: its CRC-32C"
    with pytest.raises(DatasetError, match=message):
        read(copy, "frames")
    with pytest.raises(DatasetError, match=rf"rows {row}\.\.{row} do not read back"):
        read(copy, "frames", row, row + 1)
    other = (row + 1) % ROWS  # a row whose chunk is intact still reads
    assert read(copy, "frames", other, other + 1).any()


def test_a_byte_changed_in_the_shard_index_is_damage(copy, no_zarr_reads):
    shard = file_of(copy, "frames", 1)
    flip(shard, shard.stat().st_size - INDEX_BYTES + 1)  # the high byte of entry 0's offset: far outside the shard
    with pytest.raises(DatasetError, match=r"'ring/0' is damaged: its frames rows 6\.\.11 do not read back "
                                           r"\(shard index: its CRC-32C checksum does not match\)"):
        read(copy, "frames", ROWS, 2 * ROWS, "ring/0")


@pytest.mark.parametrize("name", ["normals", "labels", "plane_points"])
def test_a_byte_changed_in_a_chunk_of_another_array_is_damage(copy, name, no_zarr_reads):
    chunk = file_of(copy, name, 0)
    flip(chunk, chunk.stat().st_size - 6)  # in the compressed data, the header intact
    with pytest.raises(DatasetError, match=rf"'box/0' is damaged: its {name} rows 0\.\.5 do not read back "
                                           r"\(chunk: its CRC-32C checksum does not match\)"):
        read(copy, name)


def test_a_frame_blosc_cannot_decode_is_damage_even_with_a_valid_checksum(copy, no_zarr_reads):
    """The frame's header kept (so it passes the header checks) and its block offsets pointed past its end: Blosc
    refuses it, and the refusal is damage, not Blosc's exception."""
    shard = file_of(copy, "frames", 0)
    offset, length = entries(shard)[2]
    data = bytearray(shard.read_bytes())
    body = offset + 16  # after the 16-byte Blosc header: the block start offsets (int32 each)
    struct.pack_into("<i", data, body, 2**31 - 1)
    data[offset + length - 4:offset + length] = google_crc32c.value(bytes(data[offset:offset + length - 4])).to_bytes(
        4, "little")
    shard.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"'box/0' is damaged: its frames rows 0\.\.5 do not read back \(RuntimeError"):
        read(copy, "frames")


def test_a_layout_decoded_here_and_one_left_to_zarr_read_the_same(tmp_path):
    """Arrays with the store's codecs: whole rows per chunk (decoded here), and inner chunks splitting a row, or
    stored big endian (left to zarr); all read as zarr reads them."""
    from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ShardingCodec

    values = np.arange(4 * 3 * 4, dtype=np.uint16).reshape(4, 3, 4) * 7
    cases = {
        "rows": ((1, 3, 4), "little", True),
        "split": ((1, 3, 2), "little", False),
        "big": ((1, 3, 4), "big", False),
    }
    for name, (inner, endian, direct) in cases.items():
        codecs = [BytesCodec(endian=endian), BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"), Crc32cCodec()]
        sharding = ShardingCodec(chunk_shape=inner, codecs=codecs,
                                 index_codecs=[BytesCodec(endian="little"), Crc32cCodec()])
        array = zarr.create_array(tmp_path / name, shape=values.shape, chunks=(2, 3, 4), dtype="uint16",
                                  serializer=sharding, compressors=None, fill_value=0,
                                  config={"write_empty_chunks": True})
        array[:] = values
        array = zarr.open_array(tmp_path / name, mode="r")
        assert store_module._chunk_plan(tmp_path, name, array).direct is direct, name
        for lo, hi in ((0, 2), (2, 4), (1, 2)):
            np.testing.assert_array_equal(read_rows(tmp_path, name, array, lo, hi, "x"), values[lo:hi])


def test_row_checksums_of_no_rows_and_of_empty_rows():
    from tactile.dataset.store import row_checksums

    assert row_checksums(np.zeros((0, 25, 3), np.float32), np.float32).tolist() == []
    assert row_checksums(np.zeros((2, 0)), np.float32).tolist() == [0, 0]  # CRC-32C of no bytes
    # labels (1-D): each row is its int64's 8 bytes; the check value of b"123456789" (RFC 3720) as a uint8 row
    assert row_checksums(np.frombuffer(b"123456789", np.uint8)[None], np.uint8).tolist() == [0xE3069283]
    assert row_checksums(np.array([1, 2]), np.int64).tolist() == [
        google_crc32c.value(np.int64(v).tobytes()) for v in (1, 2)]

def _array(path: Path, values: np.ndarray, inner: tuple, shard_rows: int, fill):
    from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec, ShardingCodec

    codecs = [BytesCodec(endian="little"), BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"), Crc32cCodec()]
    sharding = ShardingCodec(chunk_shape=inner, codecs=codecs, index_codecs=[BytesCodec(endian="little"), Crc32cCodec()])
    array = zarr.create_array(path, shape=values.shape, chunks=(shard_rows, *values.shape[1:]), dtype=values.dtype,
                              serializer=sharding, compressors=None, fill_value=fill,
                              config={"write_empty_chunks": True})
    array[:] = values
    return zarr.open_array(path, mode="r")


def test_an_absent_inner_chunk_reads_as_the_arrays_own_fill_value(tmp_path):
    """An array whose fill value is not 0: an inner chunk marked absent reads as that value, as zarr reads it."""
    values = (np.arange(4 * 3 * 4, dtype=np.uint16).reshape(4, 3, 4) + 1) * 3
    array = _array(tmp_path / "a", values, (1, 3, 4), 4, 7)
    assert store_module._chunk_plan(tmp_path, "a", array).direct
    (shard,) = [p for p in (tmp_path / "a").rglob("*") if p.is_file() and p.name != "zarr.json"]
    data = bytearray(shard.read_bytes())
    index = 4 * SHARD_ENTRY_BYTES + 4
    struct.pack_into("<QQ", data, len(data) - index + 2 * SHARD_ENTRY_BYTES, 2**64 - 1, 2**64 - 1)
    data[-4:] = google_crc32c.value(bytes(data[-index:-4])).to_bytes(4, "little")
    shard.write_bytes(bytes(data))
    by_zarr = zarr.open_array(tmp_path / "a", mode="r")[0:4]
    assert (by_zarr[2] == 7).all() and (by_zarr[1] == values[1]).all()
    np.testing.assert_array_equal(read_rows(tmp_path, "a", array, 0, 4, "x"), by_zarr)
    np.testing.assert_array_equal(read_rows(tmp_path, "a", array, 2, 3, "x"), by_zarr[2:3])


def test_shards_of_inner_chunks_holding_several_rows_are_left_to_zarr_and_read_as_it_reads_them(tmp_path):
    values = np.arange(8 * 3 * 4, dtype=np.uint16).reshape(8, 3, 4) * 5
    array = _array(tmp_path / "m", values, (2, 3, 4), 4, 0)
    assert store_module._chunk_plan(tmp_path, "m", array).direct is False
    for lo, hi in ((0, 4), (4, 8), (1, 3), (5, 6)):
        np.testing.assert_array_equal(read_rows(tmp_path, "m", array, lo, hi, "x"), values[lo:hi])


def test_update_digest_hashes_the_values_as_the_dtype_it_is_given():
    """Values in float64 added as float32: the digest of the float32 bytes (the store's), not of the float64 ones."""
    values = np.linspace(0, 1, 24).reshape(4, 6)  # float64
    digest = hashlib.sha256()
    update_digest(digest, values, np.float32)
    assert digest.hexdigest() == hashlib.sha256(values.astype(np.float32).tobytes()).hexdigest()
    digest = hashlib.sha256()
    update_digest(digest, values[:, ::2], np.float32)  # not contiguous
    assert digest.hexdigest() == hashlib.sha256(np.ascontiguousarray(values[:, ::2], np.float32).tobytes()).hexdigest()



def _early_return_then_far_entry(copy: Path, entry: tuple[int, int]) -> None:
    """Frames shard of object 0: inner chunk 0's Blosc header damaged without its CRC fixed (``_header_problem``
    then stops at it, leaving the later entries unchecked), and inner chunk 1's index entry set to ``entry`` with
    the index's CRC fixed."""
    (shard,) = store_module.chunk_files(copy, "frames", zarr.open_array(copy / "frames", mode="r"), 0, ROWS)
    data = bytearray(shard.read_bytes())
    entries = np.frombuffer(bytes(data[-INDEX_BYTES:-4]), dtype="<u8").reshape(ROWS, 2).copy()
    struct.pack_into("<I", data, int(entries[0, 0]) + 4, 12345)  # nbytes of inner chunk 0
    entries[1] = entry
    data[-INDEX_BYTES:-4] = entries.tobytes()
    data[-4:] = google_crc32c.value(bytes(data[-INDEX_BYTES:-4])).to_bytes(4, "little")
    shard.write_bytes(bytes(data))


@pytest.mark.parametrize("entry", [(2**63, 16), (0, 2**64 - 2), (0, 2**62), (0, 2**30)])
def test_an_entry_far_outside_after_a_damaged_chunk_is_damage_not_a_foreign_error(copy, entry):
    """Found by a break attempt: the rows' span was read in one go from entries never checked (OverflowError,
    MemoryError, or a 1 GiB read); every entry is now checked against the chunk data first."""
    _early_return_then_far_entry(copy, entry)
    with pytest.raises(DatasetError, match=r"'box/0' is damaged: its frames rows 0\.\.5 do not read back \(inner "
                                           r"chunk 1 lies at bytes \d+\.\.\d+, outside its \d+ bytes of chunk data\)"):
        read_rows(copy, "frames", zarr.open_array(copy / "frames", mode="r"), 0, ROWS, "box/0")

