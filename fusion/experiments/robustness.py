"""Noise: models trained on clean data (the paper protocol's), tested on held-out contours of the same objects
read with taxel noise, dead taxels or jittered probe poses, at growing levels. ``dead_taxels_repaired`` reads the
same frames as ``dead_taxels`` and repairs them (:func:`tactile.dead_taxels.repair_dead_taxels`) before the
models see them; its level 0 is the clean reading repaired (what the repair costs where nothing is broken).

Every level touches the same contours (planes and seeds from the run seed + ``TEST_SEED_OFFSET``, the object
and the strategy, :func:`fusion.experiments.touch.touch_object`), so only the perturbation differs between
levels; level 0 is the clean reading. Guided contours are drawn from the interest points the training store
recorded for the object (no saliency is recomputed). Intervals: bootstrap over test sequences.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from fusion.base import load_model
from fusion.experiments.analysis import score
from fusion.experiments.context import Context
from fusion.experiments.models import DISPLAY, predict
from fusion.experiments.touch import load_batch, save_batch, touch_objects
from fusion.modelfile import SUFFIX
from perception.errors import SaliencyError
from perception.geometry import ObjectModel
from tactile.dead_taxels import repair_dead_taxels
from tactile.sampling import STRATEGIES as METHODS
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Test contours use seed + this, so they are drawn independently of the training store's.
TEST_SEED_OFFSET = 7919


@dataclass(frozen=True, eq=False)
class StoredAttention:
    """The interest points a dataset store recorded for one object, usable where sampling wants a Saliency."""

    model: ObjectModel
    method: str
    points: np.ndarray

    def interest_points(self, n: int, **_) -> np.ndarray:
        if n > len(self.points):
            raise SaliencyError(f"{self.model.name}: the store recorded {len(self.points)} interest points, "
                                f"{n} asked for")
        return self.points[:n].copy()


def _attention(ds, models: list, strategy: str, seed: int) -> dict | None:
    """{object name: attention} of a guided-like strategy: the store's interest points, else computed."""
    method = METHODS[strategy]
    if method is None:
        return None
    out = {}
    for model in models:
        stored = ds.interest_points(model.name).get(strategy) if ds is not None else None
        if stored is not None and len(stored):
            out[model.name] = StoredAttention(model, method, stored)
        else:
            from perception.saliency import saliency

            out[model.name] = saliency(model, method, seed=seed)
    return out


def _sensor_and_jitter(kind: str, level: float) -> tuple[FSRSensor, float]:
    if kind == "taxel_noise":
        return FSRSensor(noise_std=float(level)), 0.0
    if kind in ("dead_taxels", "dead_taxels_repaired"):
        return FSRSensor(dead_taxel_rate=float(level)), 0.0
    return FSRSensor(), float(level)


def _view(kind: str) -> str:
    """Which frames a noise kind's models read: "repaired" or "raw" (as touched)."""
    return "repaired" if kind.endswith("_repaired") else "raw"


def noise_rows(ctx: Context, models: list, class_names: list[str], ds=None) -> list[dict]:
    """Accuracy rows {kind, level, strategy, classifier, accuracy} for every noise kind and level (0 included).

    Args:
        ds: the paper protocol's dataset (its recorded interest points are reused for guided contours).
    """
    sizes = ctx.sizes
    levels = [("clean", 0.0)] + [(k, float(v)) for k, vs in sizes.noise_levels.items() for v in vs]
    attention: dict[str, dict] = {}
    rows = []
    for strategy in sizes.strategies:
        estimators = {name: load_model(ctx.path("models", "paper", strategy, f"{name}{SUFFIX}"))
                      for name in sizes.paper_classifiers}
        for kind, level in levels:
            sensor, jitter = _sensor_and_jitter(kind, level)
            read = "dead_taxels" if kind == "dead_taxels_repaired" else kind  # the same frames, repaired below
            key = {"objects": [m.name for m in models], "strategy": strategy, "kind": read, "level": level,
                   "contours": sizes.noise_contours, "seed": ctx.seed + TEST_SEED_OFFSET, "sensor": sensor.spec()}
            path = ctx.path("noise", f"{strategy}-{read}-{level:g}.npz")
            batch = load_batch(path, key)
            if batch is None:
                if strategy not in attention:
                    attention[strategy] = _attention(ds, models, strategy, ctx.seed)
                batch = touch_objects(models, class_names, strategy, sizes.noise_contours, sensor=sensor,
                                      seed=ctx.seed + TEST_SEED_OFFSET, jitter_mm=jitter,
                                      attention=attention.get(strategy), progress=ctx.progress)
                save_batch(batch, path, key)
            kinds = list(sizes.noise_levels) if kind == "clean" else [kind]  # clean is level 0 of every kind
            # The frames each kind's models read: as touched, or repaired; each predicted once.
            views = {_view(k) for k in kinds}
            inputs = {"raw": batch} if "raw" in views else {}
            if "repaired" in views:
                inputs["repaired"] = replace(batch, frames=repair_dead_taxels(batch.frames, sensor))
            for name, estimator in estimators.items():
                acc = {v: score(predict(estimator, data), by="decision", seed=ctx.seed) for v, data in inputs.items()}
                for k in kinds:
                    rows.append({"kind": k, "level": level, "strategy": strategy, "classifier": DISPLAY.get(name, name),
                                 "name": name, "accuracy": acc[_view(k)].to_dict()})
    return rows


__all__ = ["TEST_SEED_OFFSET", "StoredAttention", "noise_rows"]
