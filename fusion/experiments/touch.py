"""Touching objects in-process: tactile sequences with optional probe-pose jitter, timed, cached as ``.npz``.

The dataset stores (:mod:`tactile.dataset`) hold the training and test data; this module makes the small
extra sets the experiments need and a store cannot: sequences whose probe poses are jittered (the finger
does not land where planned), per-contour timings of simulated touching, and the contours a user's mesh is
touched along (``visuotactile recognize``).

Pose jitter of level ``j`` mm: each probe's pad centre moves by N(0, j) mm along the pad's two axes and its
normal tilts by N(0, ``TILT_DEG_PER_MM`` * j) degrees about a random axis in the pad plane; the pad is
pressed at that pose, while the sequence records the *planned* pose (the robot does not know its error).
Planes and noise seeds depend only on (seed, object name, strategy), so every jitter or noise level touches
the same contours and only the perturbation differs.
"""

from __future__ import annotations

import json
import logging
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fusion.experiments.config import TILT_DEG_PER_MM
from perception.atomic import atomic_path
from perception.errors import ContourError, DatasetError
from perception.geometry import ObjectModel
from tactile.contours import Contour, make_contour
from tactile.explore import SequenceBatch, TactileSequence, explore
from tactile.sampling import STRATEGIES, sample_planes
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Extra planes drawn per object in case some miss (a plane through the centre can miss a ring's hole).
SPARE_PLANES = 20


@dataclass
class TouchTiming:
    """Wall-clock seconds of simulated touching: per contour (cut + press) and per object (saliency)."""

    contour_seconds: list[float] = field(default_factory=list)
    saliency_seconds: list[float] = field(default_factory=list)

    def median_contour(self) -> float:
        return float(np.median(self.contour_seconds)) if self.contour_seconds else 0.0

    def median_saliency(self) -> float:
        return float(np.median(self.saliency_seconds)) if self.saliency_seconds else 0.0


def object_seed(seed: int, name: str, strategy: str) -> np.random.SeedSequence:
    """The seed sequence of one object's contours: depends on (seed, object name, strategy) only."""
    return np.random.SeedSequence([int(seed), zlib.crc32(name.encode()), zlib.crc32(strategy.encode())])


def jitter_contour(contour: Contour, position_mm: float, rng: np.random.Generator) -> Contour:
    """``contour`` with each probe moved by N(0, position_mm) along the pad axes and its normal tilted by
    N(0, TILT_DEG_PER_MM * position_mm) degrees (see the module docstring); position_mm 0 returns it as is."""
    if position_mm < 0 or not np.isfinite(position_mm):
        raise DatasetError(f"pose jitter must be a finite number >= 0 mm, got {position_mm!r}")
    if position_mm == 0:
        return contour
    n = contour.n_probes
    t, b, normal = contour.tangents, contour.binormals, contour.normals
    shift = rng.normal(0.0, position_mm, (n, 2))
    positions = contour.positions + shift[:, :1] * t + shift[:, 1:] * b
    angle = np.radians(rng.normal(0.0, TILT_DEG_PER_MM * position_mm, n))[:, None]
    phi = rng.uniform(0.0, 2 * np.pi, n)[:, None]
    axis = np.cos(phi) * t + np.sin(phi) * b  # unit, in the pad plane
    normals = np.cos(angle) * normal + np.sin(angle) * axis
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tangents = t - np.sum(t * normals, axis=1, keepdims=True) * normals
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    return Contour(contour.plane, contour.polyline, contour.closed, positions, normals, tangents,
                   contour.triangle_ids)


def touch_object(
    model: ObjectModel,
    strategy: str,
    n_contours: int,
    *,
    sensor: FSRSensor | None = None,
    probes: int = 25,
    seed: int = 0,
    jitter_mm: float = 0.0,
    attention=None,
    timing: TouchTiming | None = None,
) -> tuple[list[TactileSequence], list[Contour]]:
    """``n_contours`` tactile sequences of ``model`` along contours chosen by ``strategy``, and the contours.

    Args:
        attention: a precomputed :class:`~perception.saliency.Saliency` of the strategy's method (else
            computed here, and timed into ``timing``).

    Raises:
        ContourError: unknown strategy or too many planes that miss the object.
    """
    if strategy not in STRATEGIES:
        raise ContourError(f"unknown sampling strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")
    sensor = sensor or FSRSensor()
    plane_seed, noise_seed, jitter_seed = object_seed(seed, model.name, strategy).spawn(3)
    if STRATEGIES[strategy] is not None and attention is None:
        from perception.saliency import saliency

        start = time.perf_counter()
        attention = saliency(model, STRATEGIES[strategy], seed=seed)
        if timing is not None:
            timing.saliency_seconds.append(time.perf_counter() - start)
    planes = sample_planes(model, strategy, n_contours + SPARE_PLANES, np.random.default_rng(plane_seed),
                           saliency=attention)
    contour_seeds = np.random.default_rng(noise_seed).integers(2**31 - 1, size=len(planes))
    jitter_rng = np.random.default_rng(jitter_seed)
    sequences, contours = [], []
    for plane, contour_seed in zip(planes, contour_seeds):
        if len(sequences) == n_contours:
            break
        start = time.perf_counter()
        try:
            contour = make_contour(model, plane, probes)
        except ContourError as exc:
            log.debug("%s: skipping a plane (%s)", model.name, exc)
            continue
        pressed = jitter_contour(contour, jitter_mm, jitter_rng)
        sequence = explore(model, pressed, sensor, seed=int(contour_seed), strategy=strategy)
        if timing is not None:
            timing.contour_seconds.append(time.perf_counter() - start)
        if pressed is not contour:  # record the planned pose
            sequence.normals, sequence.positions = contour.normals.copy(), contour.positions.copy()
            sequence.tangents = contour.tangents.copy()
        sequences.append(sequence)
        contours.append(contour)
    if len(sequences) < n_contours:
        raise ContourError(f"{model.name}: only {len(sequences)} of {n_contours} planes cut the object")
    return sequences, contours


def touch_objects(
    models: list[ObjectModel],
    class_names: list[str],
    strategy: str,
    n_contours: int,
    *,
    sensor: FSRSensor | None = None,
    probes: int = 25,
    seed: int = 0,
    jitter_mm: float = 0.0,
    attention: dict | None = None,
    timing: TouchTiming | None = None,
    progress: bool = False,
) -> SequenceBatch:
    """Touch every model (labels from ``model.label``) and stack the sequences; object ids follow ``models``.

    Args:
        attention: optional {model name: Saliency} to reuse.
    """
    sensor = sensor or FSRSensor()
    sequences = []
    for model in tqdm(models, desc=f"touch {strategy}", unit="obj", disable=not progress):
        found, _ = touch_object(model, strategy, n_contours, sensor=sensor, probes=probes, seed=seed,
                                jitter_mm=jitter_mm, attention=(attention or {}).get(model.name), timing=timing)
        sequences += found
    return SequenceBatch.from_sequences(sequences, class_names=list(class_names), sensor_spec=sensor.spec())


# ----------------------------------------------------------------------------------------- batch cache
_ARRAYS = ("frames", "normals", "positions", "tangents", "pad_sides_mm", "plane_points", "plane_normals",
           "labels", "object_ids")


def save_batch(batch: SequenceBatch, path: str | Path, key: dict | None = None) -> Path:
    """Write ``batch`` (and a cache ``key``) to ``path`` (.npz) atomically."""
    meta = {"class_names": list(batch.class_names), "object_names": list(batch.object_names),
            "sensor_spec": batch.sensor_spec, "key": key or {}}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, meta=np.array(json.dumps(meta, default=str)), **{a: getattr(batch, a) for a in _ARRAYS})
    return Path(path)


def load_batch(path: str | Path, key: dict | None = None) -> SequenceBatch | None:
    """The batch cached at ``path``, or None when absent, unreadable or made with another ``key``."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if key is not None and meta.get("key") != json.loads(json.dumps(key, default=str)):
                log.info("%s was made with other settings; rebuilding it", path)
                return None
            arrays = {a: data[a] for a in _ARRAYS}
    except (OSError, ValueError, KeyError) as exc:
        log.warning("%s is unreadable (%s); rebuilding it", path, exc)
        return None
    return SequenceBatch(**arrays, class_names=meta["class_names"], object_names=meta["object_names"],
                         sensor_spec=meta["sensor_spec"])


__all__ = ["TouchTiming", "jitter_contour", "load_batch", "object_seed", "save_batch", "touch_object",
           "touch_objects"]
