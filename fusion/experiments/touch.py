"""Touching objects in-process for the experiments: stacked batches cached as ``.npz``.

The dataset stores (:mod:`tactile.dataset`) hold the training and test data; this module makes the small
extra sets the experiments need and a store cannot: sequences whose probe poses are jittered (the finger
does not land where planned), per-contour timings of simulated touching, and the contours a user's mesh is
touched along (``visuotactile recognize``). The touching itself is :func:`tactile.touching.touch` with the
"object" seed scheme: planes and noise seeds depend only on (seed, object name, strategy), so every jitter or
noise level touches the same contours and only the perturbation differs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fusion.experiments.models import read_cache, write_cache
from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel
from perception.runtime import progress_bar
from tactile.contours import Contour
from tactile.explore import SequenceBatch, TactileSequence
from tactile.sensor import FSRSensor
from tactile.touching import TouchTiming, touch


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
    """``n_contours`` tactile sequences of ``model`` along contours chosen by ``strategy``, and the contours:
    :func:`tactile.touching.touch` with the "object" seed scheme.

    Args:
        attention: a precomputed :class:`~perception.saliency.Saliency` of the strategy's method (else
            computed, and timed into ``timing``).

    Raises:
        ContourError: unknown strategy or too many planes that miss the object.
    """
    contours: list[Contour] = []
    sequences = touch(model, strategy, n_contours, sensor, probes, seed, attention, seeding="object",
                      jitter_mm=jitter_mm, timing=timing, contours=contours)
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
    noise_seeds: list | None = None,
) -> SequenceBatch:
    """Touch every model (labels from ``model.label``) and stack the sequences; object ids follow ``models``.

    Args:
        attention: optional {model name: Saliency} to reuse.
        noise_seeds: if given, each sequence's read-out seed is appended to it (in the batch's order), so that
            :meth:`tactile.sensor.FSRSensor.reread` can give the frames of a noisier sensor without touching again.
    """
    sensor = sensor or FSRSensor()
    sequences = []
    for model in progress_bar(models, enabled=progress, desc=f"touch {strategy}", unit="obj"):
        found, _ = touch_object(model, strategy, n_contours, sensor=sensor, probes=probes, seed=seed,
                                jitter_mm=jitter_mm, attention=(attention or {}).get(model.name), timing=timing)
        sequences += found
    if noise_seeds is not None:
        noise_seeds.extend(s.seed for s in sequences)
    return SequenceBatch.from_sequences(sequences, class_names=list(class_names), sensor_spec=sensor.spec())


# ----------------------------------------------------------------------------------------- batch cache
_ARRAYS = ("frames", "normals", "positions", "tangents", "pad_sides_mm", "plane_points", "plane_normals",
           "labels", "object_ids")


def save_batch(batch: SequenceBatch, path: str | Path, key: dict | None = None, noise_seeds=None) -> Path:
    """Write ``batch`` (and a cache ``key``, and optionally each sequence's read-out seed) to ``path`` (.npz)
    atomically."""
    meta = {"class_names": list(batch.class_names), "object_names": list(batch.object_names),
            "sensor_spec": batch.sensor_spec, "key": key or {}}
    arrays = {a: getattr(batch, a) for a in _ARRAYS}
    if noise_seeds is not None:
        seeds = np.asarray(noise_seeds)
        if not _valid_seeds(seeds, len(batch)):
            raise InvalidArgumentError(f"{path}: noise_seeds must be one integer in [0, 2**63) per sequence "
                                       f"({len(batch)}), got shape {seeds.shape} of {seeds.dtype}")
        arrays["noise_seeds"] = seeds.astype(np.int64)
    return write_cache(path, meta, arrays)


def _valid_seeds(seeds: np.ndarray, n: int) -> bool:
    """Whether ``seeds`` are ``n`` integers in [0, 2**63) (no seeds at all for an empty batch)."""
    if seeds.shape != (n,):
        return False
    return not seeds.size or (seeds.dtype.kind in "iu" and bool((seeds >= 0).all())
                              and bool((seeds <= np.iinfo(np.int64).max).all()))


def _load(path: str | Path, key: dict | None) -> tuple[SequenceBatch, np.ndarray | None] | None:
    """(the cached batch, its stored read-out seeds or None), or None when absent, unreadable or of another key."""
    def read(meta, data):  # inside read_cache: a file missing a field counts as unreadable (made again)
        seeds = data["noise_seeds"] if "noise_seeds" in data.files else None
        batch = SequenceBatch(**{a: data[a] for a in _ARRAYS}, class_names=meta["class_names"],
                              object_names=meta["object_names"], sensor_spec=meta["sensor_spec"])
        return batch, seeds

    return read_cache(path, "key", key, read)


def load_batch(path: str | Path, key: dict | None = None) -> SequenceBatch | None:
    """The batch cached at ``path``, or None when absent, unreadable or made with another ``key``."""
    found = _load(path, key)
    return None if found is None else found[0]


def load_batch_with_seeds(path: str | Path, key: dict | None = None) -> tuple[SequenceBatch, np.ndarray] | None:
    """(the batch cached at ``path``, each sequence's read-out seed (S,) int64), or None when absent, unreadable,
    made with another ``key``, or holding no usable seeds (absent, not one non-negative integer per sequence)."""
    found = _load(path, key)
    if found is None:
        return None
    batch, seeds = found
    usable = seeds is not None and seeds.dtype.kind in "iu" and _valid_seeds(seeds, len(batch))
    return (batch, seeds.astype(np.int64)) if usable else None


__all__ = ["load_batch", "load_batch_with_seeds", "save_batch", "touch_object", "touch_objects"]
