"""Dataset benchmark: generation throughput next to the raw ray-casting limit, storage, and a DataLoader epoch.

One run measures, on the same objects and cores:

(a) Generation: :func:`tactile.dataset.generate` wall time and sequences/s with ``--workers`` processes,
    and the peak memory of the whole process tree (sum of PSS of this process and all its descendants,
    sampled every 0.2 s). Sampling reads every process's page tables and slows the generation it watches, so
    with ``--repeats`` N > 1 only the first run samples memory and the time is the median of the other N - 1.
(b) The raw limit: the same probes' full-resolution rays (one 1,024-ray pad per probe at the side the
    store recorded, i.e. the fewest rays that give those frames) cast with ``RaycastingScene.cast_rays``
    and nothing else, one process per object, ``--workers`` at a time, each on its share of the cores as the workers
    are; rays are built before the clock starts. Limit = sequences x workers / (sum of cast seconds). Ratio =
    generation rate / limit. Guided contours repeat (pairs of 10 interest points), and generation presses a repeated
    contour once, so the ratio can pass 1; the table also gives the raw time of the distinct contours alone and the
    ratio of that to the generation time (the share of generation that is the unavoidable ray casting), and the raw
    time of every ray the generation cast (each object's record counts them: the adaptive pad's survey, shrink and
    settle passes too), the floor of the algorithm as it is.
(c) Writing: the seconds the workers spent writing rows (encode, checksum, write the files) beside Blosc with
    the store's settings encoding the same bytes chunk by chunk and nothing else (both summed over workers,
    / workers).
    Storage: bytes per sequence on disk, and the frame encoding compared on stored sequences: quantised
    uint16 (the store's) against float16, each with the store's Blosc codec: max |error| and bytes.
    Reading: loading the whole store (every array, checked, frames to float32) beside zarr reading the frames codes
    alone and Blosc decoding them alone (the limit).
(d) One full DataLoader epoch (shuffled, batch 64, ``--workers`` loader processes) over the store:
    wall time, sequences/s, peak memory of the process tree.

Modes: ``--quick`` (4 catalogue objects, 20 contours, both strategies), default (SHREC 2007: 8 classes x 1
object, 100 contours), ``--paper`` (SHREC 2007: 8 classes x 3 objects, 950 contours, both strategies =
45,600 sequences). Objects: those ``visuotactile reproduce`` uses for the paper protocol
(:func:`fusion.experiments.data.folder_objects`: the first 8 classes in sorted order, the first 3 files of each),
so this store and the one the experiment generates are the same.

    .venv/bin/python -m benchmarks.dataset [--quick | --paper] [--workers N] [--out DIR] [--keep] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Self

import numpy as np

from benchmarks._common import DATA, machine
from perception.runtime import child_pids

RAYS_PER_CAST = 1 << 20


# ------------------------------------------------------------------------------------ memory
def _descendants(pid: int) -> list[int]:
    """pid and all its descendants (Linux /proc)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(child_pids(p))
    return out


def _pss_bytes(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class PeakMemory:
    """Peak summed PSS (bytes) of this process tree while the block runs (PSS splits shared pages, so
    forked workers are not counted twice)."""

    def __init__(self, interval_s: float = 0.2):
        self.interval_s, self.peak, self._stop = interval_s, 0, threading.Event()

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, sum(_pss_bytes(p) for p in _descendants(os.getpid())))
            self._stop.wait(self.interval_s)

    def __enter__(self) -> Self:
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


# ---------------------------------------------------------------------------------- raw limit
def _cast_all(model, grid, standoff, positions, normals, tangents, sides) -> tuple[int, float]:
    """Cast one full pad per probe into ``model.scene`` (rays built before the clock starts, in the scene's
    frame as the sensor builds them); (rays, cast seconds)."""
    import open3d as o3d

    per_cast = max(1, RAYS_PER_CAST // len(grid))
    rays, seconds = 0, 0.0
    for lo in range(0, len(positions), per_cast):
        sl = slice(lo, lo + per_cast)
        p = model.to_scene(positions[sl].astype(np.float64))
        n, t = model.to_scene(normals[sl], directions=True), model.to_scene(tangents[sl], directions=True)
        frames = np.zeros((len(n), 3, 6), dtype=np.float32)
        frames[:, 0, :3] = t * sides[sl, None]
        frames[:, 1, :3] = np.cross(n, t) * sides[sl, None]
        frames[:, 2, :3] = p + standoff * n  # as the sensor casts
        frames[:, 2, 3:] = -n
        tensor = o3d.core.Tensor(np.matmul(grid, frames).reshape(-1, 6))
        start = time.perf_counter()
        model.scene.cast_rays(tensor)
        seconds += time.perf_counter() - start
        rays += tensor.shape[0]
    return rays, seconds


def _raw_cast(job: tuple) -> tuple[int, float, int, float]:
    """Cast the full-resolution rays of one object's stored probes: (rays, seconds) of its distinct
    contours (each drawn contour once), then of the repeats."""
    from tactile.dataset import ObjectSpec
    from tactile.sensor import FSRSensor

    spec_dict, sensor_spec, positions, normals, tangents, sides, distinct = job
    source = {k: v for k, v in spec_dict.items() if k in ("path", "catalogue")}
    if "catalogue" in source:
        source["catalogue"] = tuple(source["catalogue"])
    model = ObjectSpec(spec_dict["name"], spec_dict["label"], **source).load()
    sensor = FSRSensor.from_spec(sensor_spec)
    grid = np.concatenate([sensor._unit_grid, np.ones((len(sensor._unit_grid), 1))], axis=1).astype(np.float32)
    casts = []
    for rows in (distinct, ~distinct):
        casts += _cast_all(model, grid, sensor.standoff_mm, positions[rows],
                           normals[rows], tangents[rows], sides[rows])
    return tuple(casts)


def raw_limit(store: Path, workers: int) -> dict:
    """Rays cast with nothing else: of every stored sequence, and of the distinct ones (a contour drawn
    again, as guided strategies do from their 10 interest points, is cast once)."""
    import multiprocessing as mp

    from tactile.dataset import open_dataset

    ds = open_dataset(store)
    specs = {o["name"]: o for o in ds.attrs["settings"]["objects"]}
    jobs, n_distinct = [], 0
    for k, name in enumerate(ds.object_names):
        batch = ds.load(np.flatnonzero(ds.object_ids == k))
        # A contour is its probe positions: the first sequence with them is the one pressed.
        _, first = np.unique(batch.positions.reshape(len(batch), -1), axis=0, return_index=True)
        distinct = np.zeros(len(batch), bool)
        distinct[first] = True
        n_distinct += len(first)
        n = len(batch) * ds.probes
        jobs.append((specs[name], ds.sensor_spec, batch.positions.reshape(n, 3), batch.normals.reshape(n, 3),
                     batch.tangents.reshape(n, 3), batch.pad_sides_mm.reshape(n), np.repeat(distinct, ds.probes)))
    from perception.runtime import limit_cores, worker_cores

    # Each process on its share of the cores, as generation's workers are (as many as objects at most): Open3D
    # spreading every process over every core casts fewer rays per second.
    with mp.get_context("forkserver").Pool(workers, limit_cores, (worker_cores(min(workers, len(jobs))),)) as pool:
        results = pool.map(_raw_cast, jobs, chunksize=1)
    rays_distinct = sum(r[0] for r in results)
    seconds_distinct = sum(r[1] for r in results)
    rays = rays_distinct + sum(r[2] for r in results)
    cast_s = seconds_distinct + sum(r[3] for r in results)
    return {
        "rays": rays,
        "cast_seconds_sum": cast_s,
        "mrays_per_s": rays / cast_s * workers / 1e6,
        "sequences_per_s": len(ds) * workers / cast_s,
        "distinct_sequences": n_distinct,
        "distinct_rays": rays_distinct,
        "distinct_cast_seconds_sum": seconds_distinct,
    }


# ----------------------------------------------------------------------------------- storage
def _store_codec():
    """Blosc with the store's settings (:data:`tactile.dataset.store.COMPRESSOR`), alone."""
    from tactile.dataset.store import compressor

    return compressor()


def storage(store: Path, n: int = 400) -> dict:
    from tactile.dataset import open_dataset

    ds = open_dataset(store)
    size = sum(p.stat().st_size for p in store.rglob("*") if p.is_file())
    frame_bytes = sum(p.stat().st_size for p in (store / "frames").rglob("*") if p.is_file())
    pick = np.sort(np.random.default_rng(0).choice(len(ds), min(n, len(ds)), replace=False))
    frames = ds.frames(pick)
    codes = np.rint(frames.astype(np.float64) / ds.attrs["settings"]["encoding"]["scale"]).astype(np.uint16)
    codec = _store_codec()
    # The stored frames are the uint16 decode; compare against what float16 would have kept of them. The
    # uint16 error bound is the encoding's (the pressed readings are not kept).
    half = frames.astype(np.float16)
    return {
        "bytes_per_sequence": size / len(ds),
        "frame_bytes_per_sequence": frame_bytes / len(ds),
        "store_bytes": size,
        "encodings": [
            {"encoding": "uint16 (store)", "max_error": ds.max_frame_error,
             "bytes_per_sequence": float(np.mean([len(codec.encode(c)) for c in codes]))},
            {"encoding": "float16", "max_error": float(np.abs(half.astype(np.float32) - frames).max()),
             "bytes_per_sequence": float(np.mean([len(codec.encode(np.ascontiguousarray(h))) for h in half]))},
            {"encoding": "float32 raw", "max_error": 0.0, "bytes_per_sequence": float(frames[0].nbytes)},
        ],
    }


def rays_cast(store: Path, raw: dict, wall: float) -> dict:
    """Every ray the generation cast (the objects' records, ``rays``: the survey, shrink and settle passes of the
    adaptive pad included) and how long they take at the raw rate measured in the same run: the casting floor of
    the algorithm as it is, beside the floor of the distinct contours' final pads above."""
    from tactile.dataset import open_dataset
    from tactile.dataset.store import read_records

    ds = open_dataset(store)
    rays = sum(int(r.get("rays", 0)) for r in read_records(store, len(ds.object_names)).values())
    floor = rays / (raw["mrays_per_s"] * 1e6)
    probes = raw["distinct_sequences"] * ds.probes
    return {"rays": rays, "per_distinct_probe": rays / probes if probes else None, "floor_seconds": floor,
            "ratio": floor / wall if wall > 0 else None}


def writing(store: Path, workers: int) -> dict:
    """The generation's writing stage beside its limit: the seconds the workers spent writing rows
    (each object's record, ``write_seconds``; summed, / workers) and Blosc with the store's settings encoding
    the same bytes, chunk by chunk as the store holds them, and nothing else (summed, / workers)."""
    import zarr

    from tactile.dataset import open_dataset
    from tactile.dataset.store import ARRAYS, read_records

    records = read_records(store, len(open_dataset(store).object_names)).values()
    codec = _store_codec()
    encode_s, raw_bytes = 0.0, 0
    for name in ARRAYS:
        array = zarr.open_array(f"{store}/{name}", mode="r")
        rows = int(array.chunks[0])
        block = rows * max(1, 1024 // rows)  # read many chunks at once, encode them one by one
        for start in range(0, array.shape[0], block):
            values = array[start:start + block]
            for lo in range(0, len(values), rows):
                chunk = np.ascontiguousarray(values[lo:lo + rows])
                started = time.perf_counter()
                codec.encode(chunk)
                encode_s += time.perf_counter() - started
                raw_bytes += chunk.nbytes
    write_s = sum(float(r.get("write_seconds", 0.0)) for r in records)
    return {"write_seconds": write_s / workers, "blosc_seconds": encode_s / workers, "raw_bytes": raw_bytes,
            "ratio": (encode_s / write_s) if write_s > 0 else None}


# ------------------------------------------------------------------------------------------ reading
def reading(store: Path, repeats: int = 3) -> dict:
    """Loading the whole store (``TactileDataset.load``: every array, checked, frames decoded to float32; median of
    ``repeats``) beside two references on the same files: zarr reading the frames codes alone (object by object, as
    loading did until 2026-11-28) and the limit, Blosc decoding every frames chunk from bytes already in memory and
    nothing else."""
    import zarr

    from tactile.dataset import open_dataset
    from tactile.dataset.store import CRC_BYTES, SHARD_ENTRY_BYTES, ZARR_READ, rows_per_file

    ds = open_dataset(store)
    load_s = []
    for _ in range(repeats):
        started = time.perf_counter()
        ds.load()
        load_s.append(time.perf_counter() - started)
    frames = zarr.open_array(f"{store}/frames", mode="r")
    per = rows_per_file(frames)
    started = time.perf_counter()
    with zarr.config.set(ZARR_READ):
        for lo in range(0, frames.shape[0], per):
            frames[lo:lo + per]
    zarr_s = time.perf_counter() - started
    codec, blosc_s, raw_bytes = _store_codec(), 0.0, 0
    for shard in sorted(p for p in (store / "frames").rglob("*") if p.is_file() and p.name != "zarr.json"):
        data = shard.read_bytes()
        index = np.frombuffer(data[-(per * SHARD_ENTRY_BYTES + CRC_BYTES):-CRC_BYTES], dtype="<u8").reshape(-1, 2)
        chunks = [data[o:o + n - CRC_BYTES] for o, n in index.tolist() if n != 2**64 - 1]
        started = time.perf_counter()
        for chunk in chunks:
            raw_bytes += len(codec.decode(chunk))
        blosc_s += time.perf_counter() - started
    load = statistics.median(load_s)
    return {"sequences": len(ds), "load_seconds": load, "load_seconds_all": load_s, "zarr_frames_seconds": zarr_s,
            "blosc_seconds": blosc_s, "raw_bytes": raw_bytes, "ratio": blosc_s / load}


# ---------------------------------------------------------------------------------- DataLoader
def loader_epoch(store: Path, workers: int, batch_size: int = 64) -> dict:
    import torch

    from tactile.dataset import open_dataset

    ds = open_dataset(store)
    with PeakMemory() as mem:
        start = time.perf_counter()
        loader = torch.utils.data.DataLoader(
            ds.torch_dataset(), batch_size=batch_size, shuffle=True, num_workers=workers,
            generator=torch.Generator().manual_seed(0), multiprocessing_context="forkserver" if workers else None,
        )
        seen = 0
        for frames, _probe, _labels in loader:
            seen += len(frames)
        seconds = time.perf_counter() - start
    assert seen == len(ds)
    return {"sequences": seen, "seconds": seconds, "sequences_per_s": seen / seconds, "peak_bytes": mem.peak,
            "loader_workers": workers, "batch_size": batch_size}


# ------------------------------------------------------------------------------------------ main
def _objects(mode: str) -> tuple[list, dict]:
    from fusion.experiments.config import FULL
    from fusion.experiments.data import folder_objects

    if mode == "quick":
        return [("box", 0), ("mug", 0), ("can", 0), ("bottle", 0)], {"contours_per_object": 20}
    per_class, contours = (FULL.objects_per_class, FULL.paper_contours) if mode == "paper" else (1, 100)
    objects = folder_objects(DATA / "shrec07", per_class=per_class, max_classes=FULL.paper_classes)
    return objects, {"contours_per_object": contours}


def run(mode: str, workers: int, out: Path | None, keep: bool, repeats: int) -> dict:
    from tactile.dataset import generate

    objects, kwargs = _objects(mode)
    folder = Path(out) if out else Path(tempfile.mkdtemp(prefix="bench-dataset-"))
    result = {"machine": machine(), "mode": mode, "workers": workers,
              "objects": [f"{o[1]}/{Path(o[0]).stem}" if mode != "quick" else f"{o[0]}/{o[1]}" for o in objects]}
    gen_times, peak = [], 0
    try:
        for r in range(repeats):
            store = folder / f"store-{r}"
            shutil.rmtree(store, ignore_errors=True)
            with PeakMemory() if r == 0 else contextlib.nullcontext() as mem:
                report = generate(objects, store, strategies=("guided", "blind"), workers=workers,
                                  progress=sys.stderr.isatty(), **kwargs)
            if report.failed:
                result["failed"] = report.failed
            gen_times.append(report.seconds)
            if r == 0:
                peak = mem.peak
            if r:
                shutil.rmtree(store)  # keep the first for the other measurements
        store = folder / "store-0"
        sequences = report.sequences
        timed = gen_times[1:] or gen_times  # the runs that did not sample memory, when there are any
        wall = statistics.median(timed)
        result["generation"] = {"sequences": sequences, "seconds": wall, "seconds_all": gen_times,
                                "seconds_timed": timed, "sequences_per_s": sequences / wall, "peak_bytes": peak}
        result["raw"] = raw_limit(store, workers)
        result["ratio_to_raw"] = result["generation"]["sequences_per_s"] / result["raw"]["sequences_per_s"]
        # The work that has to be done: the distinct contours' rays, cast on the same cores.
        raw_distinct_wall = result["raw"]["distinct_cast_seconds_sum"] / workers
        result["ratio_to_raw_distinct"] = raw_distinct_wall / wall
        result["rays_cast"] = rays_cast(store, result["raw"], wall)
        result["storage"] = storage(store)
        result["writing"] = writing(store, workers)
        result["reading"] = reading(store)
        result["loader"] = loader_epoch(store, workers)
    finally:
        if not keep:  # only what this run made: --out may hold other files
            for r in range(repeats):
                shutil.rmtree(folder / f"store-{r}", ignore_errors=True)
            if out is None:
                shutil.rmtree(folder, ignore_errors=True)
    return result


def _print(result: dict) -> None:
    g, raw, s, ld = result["generation"], result["raw"], result["storage"], result["loader"]
    print(f"\ndataset benchmark ({result['mode']}): {len(result['objects'])} objects, {g['sequences']} sequences, "
          f"{result['workers']} workers")
    print(f"  generation      {g['seconds']:8.1f} s  {g['sequences_per_s']:8.1f} seq/s   peak memory "
          f"{g['peak_bytes'] / 2**30:.2f} GiB")
    print(f"  raw cast_rays   {g['sequences'] / raw['sequences_per_s']:8.1f} s  {raw['sequences_per_s']:8.1f} seq/s "
          f"  ({raw['mrays_per_s']:.2f} Mrays/s on {result['workers']} workers)")
    print(f"  ratio to raw    {result['ratio_to_raw']:.2f}")
    print(f"  distinct        {raw['distinct_sequences']} sequences (a repeated contour is pressed once): raw "
          f"{raw['distinct_cast_seconds_sum'] / result['workers']:.1f} s, ratio {result['ratio_to_raw_distinct']:.2f}")
    c = result["rays_cast"]
    print(f"  all rays cast   {c['rays'] / 1e6:.1f} M ({c['per_distinct_probe']:.0f} per distinct probe: survey, shrink "
          f"and settle passes too): raw {c['floor_seconds']:.1f} s, ratio {c['ratio']:.2f}")
    w = result["writing"]
    ratio = "n/a" if w["ratio"] is None else f"{w['ratio']:.2f}"
    print(f"  writing         {w['write_seconds']:8.2f} s  raw Blosc of the same {w['raw_bytes'] / 1e6:.0f} MB "
          f"{w['blosc_seconds']:.2f} s, ratio {ratio}")
    r = result["reading"]
    print(f"  loading         {r['load_seconds']:8.2f} s  (all {r['sequences']} sequences, checked, float32) zarr "
          f"reading the frames alone {r['zarr_frames_seconds']:.2f} s, raw Blosc decoding them "
          f"{r['blosc_seconds']:.2f} s, ratio {r['ratio']:.2f}")
    print(f"  store           {s['bytes_per_sequence']:8.0f} bytes/sequence ({s['frame_bytes_per_sequence']:.0f} "
          f"of them frames), {s['store_bytes'] / 1e6:.1f} MB")
    for e in s["encodings"]:
        print(f"    {e['encoding']:16s} max error {e['max_error']:.2e}  {e['bytes_per_sequence']:8.0f} bytes/sequence")
    print(f"  DataLoader epoch {ld['seconds']:7.1f} s  {ld['sequences_per_s']:8.1f} seq/s   peak memory "
          f"{ld['peak_bytes'] / 2**30:.2f} GiB ({ld['loader_workers']} loader workers, batch {ld['batch_size']})")
    if result.get("failed"):
        print(f"  failed objects: {result['failed']}")
    m = result["machine"]
    print(f"machine: {m['platform']}, {m['cores_available']} of {m['cpu_count']} cores")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.dataset", description=__doc__.split("\n")[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="4 catalogue objects, 20 contours")
    mode.add_argument("--paper", action="store_true", help="SHREC 8 classes x 3 objects x 950 contours x 2 strategies")
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: usable cores)")
    parser.add_argument("--repeats", type=int, default=1, help="generation repeats (median wall time of all but the "
                        "first, which samples memory, when more than one)")
    parser.add_argument("--out", type=Path, default=None, help="folder for the stores (default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the store(s)")
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    args = parser.parse_args(argv)
    name = "quick" if args.quick else "paper" if args.paper else "default"
    if name != "quick" and not (DATA / "shrec07").is_dir():
        print(f"{DATA / 'shrec07'} is absent: use --quick (catalogue objects)")
        return 2
    workers = args.workers or len(os.sched_getaffinity(0))
    result = run(name, workers, args.out, args.keep, max(1, args.repeats))
    _print(result)
    if args.json:
        print(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
