"""Blosc decompression bombs in a store: a chunk of a few KB (within what its rows can take, its CRC-32C valid) whose
Blosc header declares far more bytes than its rows hold is refused from its header, as damage naming the object,
before zarr decompresses it (zarr decodes 64 chunks at a time: many such chunks could take gigabytes); so is a shard
index entry outside its shard, and an array whose codecs are not the store's. Reads of a bomb run in a child process
whose peak memory is measured, under an address-space limit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import google_crc32c
import numpy as np
import pytest
import zarr

from perception.errors import DatasetError
from tactile.dataset import open_dataset
from tactile.dataset.store import ARRAYS, max_chunk_file_bytes, read_rows

ROOT = Path(__file__).resolve().parents[2]
ROWS = 6  # rows per object: one frames shard of 6 inner chunks, one chunk of each other array
#: What a bomb declares once decompressed: thousands of times a chunk's raw bytes, yet its frame (one Blosc block of
#: zstd blocks of zeros, a few bytes per 128 KB) fits a chunk file's size limit (max_chunk_file_bytes) here.
BOMB_BYTES = 48 << 20
#: The most reading a refused bomb may add to the child's peak memory (decompressing it would add BOMB_BYTES).
GROWTH_LIMIT = 12 << 20


@pytest.fixture(scope="module")
def bomb() -> bytes:
    """A chunk as the stores written until 2026-11-27 hold them (Blosc zstd level 1, byte shuffle; its CRC-32C; any
    Blosc codec reads) of BOMB_BYTES zeros."""
    from numcodecs import Blosc

    codec = Blosc(cname="zstd", clevel=1, shuffle=Blosc.SHUFFLE, blocksize=BOMB_BYTES)
    return with_crc(bytes(codec.encode(np.zeros(BOMB_BYTES, dtype=np.uint8))))


def with_crc(body: bytes) -> bytes:
    return body + google_crc32c.value(body).to_bytes(4, "little")


def chunk_file(store: Path, name: str, obj: int) -> Path:
    """The chunk file of object ``obj``'s rows of array ``name`` (a frames shard, or a chunk of another array)."""
    array = zarr.open_array(store / name, mode="r")
    return store / name / array.metadata.encode_chunk_key((obj, *(0,) * (array.ndim - 1)))


def shard_chunks(shard: Path) -> list[bytes]:
    """The inner chunks of a frames shard (ROWS of them, index at its end: (offset, length) uint64s, CRC-32C)."""
    data = shard.read_bytes()
    index = data[-(16 * ROWS + 4):-4]
    assert google_crc32c.value(index) == int.from_bytes(data[-4:], "little")  # the layout this file assumes
    return [data[o:o + n] for o, n in np.frombuffer(index, dtype="<u8").reshape(ROWS, 2).tolist()]


def write_shard(shard: Path, chunks: list[bytes], entries: list[tuple[int, int]] | None = None) -> None:
    """Write ``chunks`` as a shard, with their index (or ``entries``) and its valid CRC-32C."""
    offsets = np.cumsum([0] + [len(c) for c in chunks[:-1]]).tolist()
    entries = entries or [(o, len(c)) for o, c in zip(offsets, chunks)]
    shard.write_bytes(b"".join(chunks) + with_crc(np.array(entries, dtype="<u8").tobytes()))


def load_in_child(store: Path, rows: list[int], control: list[int]) -> dict:
    """Open ``store`` and load sequences ``control`` (first uses paid, under the limit), then load ``rows`` in a child
    Python limited to its address space after the imports + 512 MiB. Returns {"error", "growth"}: the DatasetError
    (None if none) and how far that load raised the peak resident memory."""
    script = textwrap.dedent(f"""
        import json, resource, sys
        import numpy as np, zarr  # noqa: F401 -- before the limit
        from perception.errors import DatasetError
        from tactile.dataset import open_dataset

        def status(key):
            with open("/proc/self/status") as f:
                return next(int(line.split()[1]) for line in f if line.startswith(key + ":")) * 1024

        limit = status("VmSize") + (512 << 20)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        ds = open_dataset({str(store)!r})
        ds.load(np.array({control!r}))
        try:
            with open("/proc/self/clear_refs", "w") as f:  # peak resident memory := resident memory now
                f.write("5")
        except OSError:
            pass
        before = status("VmHWM")
        try:
            ds.load(np.array({rows!r}))
            error = None
        except DatasetError as exc:
            error = str(exc)
        print(json.dumps({{"error": error, "growth": status("VmHWM") - before}}))
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "MALLOC_ARENA_MAX": "2"}, check=False)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-1500:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def assert_refused(result: dict, *words: str) -> None:
    assert result["error"] is not None and "'box/0' is damaged" in result["error"], result
    assert all(word in result["error"] for word in words), result
    assert result["growth"] < GROWTH_LIMIT, f"the refused read took {result['growth'] >> 20} MiB: {result}"


# ------------------------------------------------------------------------------------------- bombs
def test_a_bomb_chunk_of_an_unsharded_array_is_refused_undecoded(copy, bomb):
    """box/0's normals chunk replaced by a bomb that passes the size and checksum checks: zarr decompressed all of it
    (BOMB_BYTES) before finding it the wrong shape."""
    chunk = chunk_file(copy, "normals", 0)
    assert len(bomb) <= max_chunk_file_bytes(zarr.open_array(copy / "normals", mode="r"))  # not refused by size
    chunk.write_bytes(bomb)
    result = load_in_child(copy, list(range(ROWS)), control=list(range(ROWS, 2 * ROWS)))
    assert_refused(result, chunk.relative_to(copy).as_posix(), f"declares {BOMB_BYTES} bytes")


def test_a_bomb_inner_chunk_in_a_frames_shard_is_refused_undecoded(copy, store, bomb):
    """Sequence 3 of box/0 replaced by a bomb inside its frames shard (its index and checksums rewritten, valid):
    reading it, or all of the object, is refused from its header; the shard's other sequences still read."""
    shard = chunk_file(copy, "frames", 0)
    chunks = shard_chunks(shard)
    chunks[3] = bomb
    write_shard(shard, chunks)
    assert shard.stat().st_size <= max_chunk_file_bytes(zarr.open_array(copy / "frames", mode="r"))
    for rows in ([3], list(range(ROWS))):
        assert_refused(load_in_child(copy, rows, control=[ROWS]), shard.relative_to(copy).as_posix(),
                       f"declares {BOMB_BYTES} bytes")
    for rows in ([0, 1, 2], [4, 5]):  # a read decodes the range of its rows in a shard: these leave sequence 3 out
        np.testing.assert_array_equal(open_dataset(copy).load(np.array(rows)).frames,
                                      open_dataset(store).load(np.array(rows)).frames)


@pytest.mark.parametrize("entry", [(1 << 40, 100), (0, 1 << 40)], ids=["offset", "length"])
def test_a_shard_index_entry_outside_its_shard_is_damage(copy, entry):
    """An index entry (valid checksum) pointing past the shard's data: zarr read from it whatever the file held there
    (an entry of 1 TB asked it to read 1 TB); it is damage, named, refused before reading."""
    shard = chunk_file(copy, "frames", 0)
    chunks = shard_chunks(shard)
    offsets = np.cumsum([0] + [len(c) for c in chunks[:-1]]).tolist()
    entries = [(o, len(c)) for o, c in zip(offsets, chunks)]
    entries[2] = entry
    write_shard(shard, chunks, entries)
    assert_refused(load_in_child(copy, [2], control=[ROWS]), "outside")


@pytest.mark.parametrize("array, edit", [
    ("normals", lambda meta: meta["codecs"].__setitem__(1, {"name": "gzip", "configuration": {"level": 1}})),
    ("frames", lambda meta: meta["codecs"][0]["configuration"].__setitem__("index_location", "start")),
], ids=["gzip", "index-at-start"])
def test_an_array_with_other_codecs_is_refused(copy, array, edit):
    """zarr.json naming another compressor (a gzip bomb would pass the Blosc check) or another shard index layout
    (read elsewhere by zarr than by the check) is refused."""
    meta_file = copy / array / "zarr.json"
    meta = json.loads(meta_file.read_text())
    edit(meta)
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=f"the '{array}' array's codecs"):
        open_dataset(copy).load(np.arange(ROWS))


# ------------------------------------------------------------------------------------------- clean stores
def test_a_clean_store_reads_identically(store, copy):
    """Every array read through the checks equals zarr's own read, by object and by single row, also with a frames
    shard laid out again (its inner chunks in another order: the index, not the order, places them)."""
    shard = chunk_file(copy, "frames", 1)
    chunks = shard_chunks(shard)
    order = [5, 3, 1, 0, 2, 4]
    offsets = dict(zip(order, np.cumsum([0] + [len(chunks[k]) for k in order[:-1]]).tolist()))
    write_shard(shard, [chunks[k] for k in order], [(offsets[k], len(chunks[k])) for k in range(ROWS)])
    for path in (store, copy):
        for name in ARRAYS:
            array = zarr.open_array(path / name, mode="r")
            whole = zarr.open_array(store / name, mode="r")[:]
            for obj, owner in enumerate(("box/0", "ring/0")):
                np.testing.assert_array_equal(read_rows(path, name, array, obj * ROWS, (obj + 1) * ROWS, owner),
                                              whole[obj * ROWS:(obj + 1) * ROWS])
            for row in (0, 4, ROWS + 2, 2 * ROWS - 1):
                np.testing.assert_array_equal(read_rows(path, name, array, row, row + 1, "x"), whole[row:row + 1])
    np.testing.assert_array_equal(open_dataset(copy).load().frames, open_dataset(store).load().frames)
