"""Exploring one object into its rows of a store: what every worker (local process or Ray task) runs.

Sequence k of strategy s of an object is, by construction, what
``touch(model, s, 1, sensor, probes, seed=contour_seed(seed, name, s, k), saliency=...)`` returns (the
"stream" seed scheme of :mod:`tactile.touching`, run by one :class:`~tactile.touching.Toucher` per strategy);
for a guided strategy the same call with ``planes=[toucher.pair_order(pair_order_seed(seed, name, s))[k]]``
(row k takes position k of the object's pair order: pairs without repeats). All contours of one strategy are
drawn first (a plane drawn again is cut once: 10 interest points give at most 45 planes, so 950 guided rows
take each about 21 times), then pressed in large batches
(:meth:`~tactile.sensor.FSRSensor.press_contours`: one adaptive pass, each contour read out with its own seed,
the same frames as one press per contour). When the sensor has no noise and no dead taxels its read-out does
not use the seed, so a repeated contour is pressed once.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from perception.errors import ContourError
from perception.geometry import ObjectModel
from perception.interest_cache import InterestPointCache
from tactile import sampling
from tactile.contours import Contour
from tactile.dataset.objects import ObjectSpec
from tactile.dataset.store import (
    ARRAYS,
    ROW_CHECKED_ARRAYS,
    array_digest,
    contour_seed,
    encode_frames,
    encode_row_checksums,
    interest_points_of,
    layout_of,
    open_for_writing,
    pair_order_seed,
    row_checksums,
    settings_digest,
    update_digest,
    value_problem,
    write_record,
    write_rows,
)
from tactile.sensor import FSRSensor, rays_cast
from tactile.touching import Toucher

log = logging.getLogger(__name__)

#: Contours pressed per batch (25 probes each: ~6,000 probes, ~25 MB of float32 frames).
PRESS_BATCH = 256


def _seed_free(sensor: FSRSensor) -> bool:
    """Whether the sensor's read-out ignores the seed (no taxel noise, no dead taxels): then one batched
    press gives the same frames as one press per contour, and a repeated contour need be pressed once."""
    return sensor.noise_std == 0 and sensor.dead_taxel_rate == 0


def _distinct(sensor: FSRSensor, contours: list[Contour]) -> tuple[np.ndarray, np.ndarray]:
    """Rows to press (the first row of each distinct contour; every row when the read-out needs its seed)
    and, per row, the index into them of the press that gives its frames. A contour drawn several times is
    the same Contour object, from the cut cache."""
    if not _seed_free(sensor):
        return np.arange(len(contours)), np.arange(len(contours))
    first: dict[int, int] = {}
    which = np.array([first.setdefault(id(c), len(first)) for c in contours], dtype=np.int64)
    _, rows = np.unique(which, return_index=True)
    return rows, which


def _press(sensor: FSRSensor, model: ObjectModel, contours: list[Contour], noise_seeds) -> tuple:
    """Frames (N, P, R, C) float32 and pad sides (N, P) of the contours, as ``explore`` gives them (one
    adaptive pass for all, each read out with its seed)."""
    pressed = sensor.press_contours(model, contours, [int(s) for s in noise_seeds])
    return np.stack([f for f, _ in pressed]), np.stack([s for _, s in pressed])


def explore_into_store(
    store: str,
    index: int,
    spec: ObjectSpec,
    settings: dict,
    sensor: FSRSensor,
    progress: Callable[[int], None] | None = None,
    saliency_cache: str | None = None,
) -> dict:
    """Explore object ``index`` (``spec``) with every strategy of ``settings``, write its rows, then its
    completion record with the digest of each array's rows (see :mod:`tactile.dataset.store`); returns the record.
    With ``saliency_cache`` (a folder, :class:`~perception.interest_cache.InterestPointCache`), interest points
    found there are used instead of computing the saliency, and those computed are kept there.

    Raises:
        whatever loading, saliency or exploring the object raises (the caller records it as failed).
    """
    start, rays_before = time.perf_counter(), rays_cast()
    layout = layout_of(settings)
    probes, seed = int(settings["probes"]), int(settings["seed"])
    label = settings["class_names"].index(spec.label)
    model = spec.load()
    sampling.check_not_flat(model)  # as touch: a flat plate fails at once, not after MAX_DRAWS
    # Named, not listed: listing the group would trip over the records folder (not a zarr node).
    arrays = {name: open_for_writing(store, name) for name in ARRAYS}
    digests = {name: array_digest() for name in ARRAYS}
    sums: dict[str, list] = {name: [] for name in ROW_CHECKED_ARRAYS}  # per strategy, in row order
    saliencies: dict = {}  # one per method, shared by the strategies using it
    interest: dict[str, list] = {}
    cache = None if saliency_cache is None else InterestPointCache(saliency_cache)
    write_seconds = 0.0  # encoding and writing the rows (benchmarks.dataset sets it beside raw Blosc)
    for s, strategy in enumerate(layout.strategies):
        method = sampling.STRATEGIES[strategy]
        found = saliencies.get(method)
        if found is None and method is not None and cache is not None:
            found = cache.known(model, method, 0, min(sampling.INTEREST_POOL, model.n_vertices))
        toucher = Toucher(model, strategy, probes=probes, saliency=found)  # saliency seed 0, as the cache's
        if method is not None:
            if found is None and cache is not None:
                cache.put(model, method, 0, toucher.points)
            saliencies[method] = toucher.saliency
            interest[strategy] = toucher.points.tolist()
            try:  # what a reader refuses, never written
                interest_points_of({"interest_points": interest}, layout.strategies)
            except (TypeError, ValueError) as exc:
                raise ContourError(f"{spec.name} ({strategy}): {exc}; nothing was written") from None
        order_seed = pair_order_seed(seed, spec.name, strategy) if toucher.guided else None
        rows = layout.rows(index, s)
        n = layout.contours
        out = {
            "frames": np.empty((n, probes, sensor.rows, sensor.cols), np.uint16),
            "pad_sides_mm": np.empty((n, probes), np.float32),
            **{a: np.empty((n, probes, 3), np.float32) for a in ("normals", "positions", "tangents")},
            "plane_points": np.empty((n, 3)), "plane_normals": np.empty((n, 3)),
            "contour_seeds": np.empty(n, np.int64), "noise_seeds": np.empty(n, np.int64),
        }
        contours = []
        for k in range(n):
            cseed = contour_seed(seed, spec.name, strategy, k)
            (planned,) = toucher.stream(1, cseed, order_seed=order_seed, start=k)
            contour, nseed = planned.contour, planned.noise_seed
            contours.append(contour)
            out["contour_seeds"][k], out["noise_seeds"][k] = cseed, nseed
            out["plane_points"][k], out["plane_normals"][k] = contour.plane.point, contour.plane.normal
            for a in ("normals", "positions", "tangents"):
                out[a][k] = getattr(contour, a)
        pressed, which = _distinct(sensor, contours)
        for lo in range(0, len(pressed), PRESS_BATCH):
            hi = min(lo + PRESS_BATCH, len(pressed))
            batch = pressed[lo:hi]
            frames, sides = _press(sensor, model, [contours[k] for k in batch], out["noise_seeds"][batch])
            done = np.flatnonzero((which >= lo) & (which < hi))
            encoded = encode_frames(frames, settings["encoding"], f"{spec.name} ({strategy})")
            out["frames"][done] = encoded[which[done] - lo]
            out["pad_sides_mm"][done] = sides[which[done] - lo]
            if progress is not None:
                progress(len(done))
        out["labels"] = np.full(n, label, np.int64)
        out["object_ids"] = np.full(n, index, np.int64)
        out["strategies"] = np.full(n, s, np.int8)
        for name, values in out.items():
            if name not in ("labels", "object_ids", "strategies", "contour_seeds", "noise_seeds") and not (
                np.isfinite(values).all()
            ):
                raise ContourError(f"{spec.name} ({strategy}): {name} contain NaN or Inf; nothing was written")
            bad = value_problem(name, values)  # what a reader refuses, never written (an object 2 km off its origin)
            if bad is not None:
                raise ContourError(f"{spec.name} ({strategy}): its {name} row {bad[0]} {bad[1]}; nothing was written")
        for name, values in out.items():
            started = time.perf_counter()
            write_rows(store, name, arrays[name], rows, values)
            write_seconds += time.perf_counter() - started
            update_digest(digests[name], values, arrays[name].dtype)  # strategies in row order
            if name in ROW_CHECKED_ARRAYS:
                sums[name].append(row_checksums(values, arrays[name].dtype))
    record = {
        "index": index,
        "name": spec.name,
        "label": spec.label,
        "status": "complete",
        "sequences": layout.block,
        "vertices": model.n_vertices,
        "triangles": model.n_triangles,
        "interest_points": interest,
        "digests": {name: digest.hexdigest() for name, digest in digests.items()},
        "row_checksums": {name: encode_row_checksums(np.concatenate(parts)) for name, parts in sums.items()},
        "settings_sha256": settings_digest(settings),
        "seconds": round(time.perf_counter() - start, 3),
        "write_seconds": round(write_seconds, 4),
        "rays": rays_cast() - rays_before,  # every ray its pads cast (benchmarks.dataset's casting floor)
    }
    write_record(store, index, record)
    return record


__all__ = ["PRESS_BATCH", "explore_into_store"]
