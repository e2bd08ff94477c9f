"""Touching objects in-process for the experiments: stacked batches cached as ``.npz``.

The dataset stores (:mod:`tactile.dataset`) hold the training and test data; this module makes the small
extra sets the experiments need and a store cannot: sequences whose probe poses are jittered (the finger
does not land where planned), per-contour timings of simulated touching, and the contours a user's mesh is
touched along (``visuotactile recognize``). The touching itself is :func:`tactile.touching.touch` with the
"object" seed scheme: planes and noise seeds depend only on (seed, object name, strategy), so every jitter or
noise level touches the same contours and only the perturbation differs.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from perception.atomic import atomic_path
from perception.geometry import ObjectModel
from perception.runtime import progress_bar
from tactile.contours import Contour
from tactile.explore import SequenceBatch, TactileSequence
from tactile.sensor import FSRSensor
from tactile.touching import TouchTiming, touch

log = logging.getLogger(__name__)


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
) -> SequenceBatch:
    """Touch every model (labels from ``model.label``) and stack the sequences; object ids follow ``models``.

    Args:
        attention: optional {model name: Saliency} to reuse.
    """
    sensor = sensor or FSRSensor()
    sequences = []
    for model in progress_bar(models, enabled=progress, desc=f"touch {strategy}", unit="obj"):
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


__all__ = ["load_batch", "save_batch", "touch_object", "touch_objects"]
