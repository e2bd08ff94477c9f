"""Noise: models trained on clean data (the unseen-objects part's fold models), tested on objects they never
saw (each fold's test objects), each in its random pose (:data:`NOISE_POSES`), along contours of their own, read
with taxel noise, dead taxels or jittered probe poses, at growing levels. ``dead_taxels_repaired`` reads the
same frames as ``dead_taxels`` and repairs them (:func:`tactile.dead_taxels.repair_dead_taxels`) before the
models see them; its level 0 is the clean reading repaired (what the repair costs where nothing is broken).

Every level touches the same contours (planes and seeds from the run seed + ``TEST_SEED_OFFSET``, the object
and the strategy, :func:`fusion.experiments.touch.touch_object`), so only the perturbation differs between
levels; level 0 is the clean reading. Read-out noise (taxel noise, dead taxels) moves no pad, so those
levels re-read the clean frames with each sequence's own seed (:meth:`tactile.sensor.FSRSensor.reread`, bit
for bit what touching again gives); only pose jitter touches again. Guided contours are drawn from the interest
points the store recorded for the object in that pose (no saliency is recomputed). Intervals: bootstrap over
objects.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fusion.base import load_model
from fusion.experiments.analysis import score
from fusion.experiments.config import Sizes
from fusion.experiments.context import Context
from fusion.experiments.data import any_pose, load_models
from fusion.experiments.models import DISPLAY, Predictions, digest, predict
from fusion.experiments.protocol import fold_folder, pose_stores
from fusion.experiments.touch import load_batch_with_seeds, save_batch, touch_objects
from fusion.modelfile import SUFFIX
from perception.interest_cache import KnownInterestPoints
from tactile.dead_taxels import repair_dead_taxels
from tactile.explore import SequenceBatch
from tactile.sampling import STRATEGIES as METHODS
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Test contours use seed + this, so they are drawn independently of the training store's.
TEST_SEED_OFFSET = 7919

#: The poses the noise part tests in. Only the robot's world: a robot never sees a data set's pose, and the
#: unseen-objects part already shows that nothing sees it (its upright and any-pose decisions are equal for every
#: classifier, strategy and K; in the full run of 2026-12-07 the noise part's 96 upright rows equalled its 96 any-pose
#: rows, intervals included), so an upright half would repeat its numbers at the cost of touching every test object
#: again at every level. This holds for pose-free classifiers, the unseen part's (``Sizes.unseen_classifiers``); a
#: classifier that reads the pose (a ``-normals`` one) would need the upright half back.
NOISE_POSES = ("any pose",)


def _attention(ds, models: list, strategy: str, seed: int) -> dict | None:
    """{object name: attention} of a guided-like strategy: the store's interest points, else computed."""
    method = METHODS[strategy]
    if method is None:
        return None
    out = {}
    for model in models:
        stored = ds.interest_points(model.name).get(strategy) if ds is not None else None
        if stored is not None and len(stored):
            out[model.name] = KnownInterestPoints(model, method, stored)
        else:
            from perception.saliency import saliency

            out[model.name] = saliency(model, method, seed=seed)
    return out


def _on_every_core(model):
    """``model`` predicting on every core the process it runs in may use (a worker's share when the part's jobs run
    on the run's workers, every core in this process with one worker): a CNN trained on one thread gives the same
    probabilities on any thread count (tests/fusion/test_cnn.py)."""
    if "threads" in model.get_params(deep=False):
        model.set_params(threads=None)
    return model


def _sensor_and_jitter(kind: str, level: float) -> tuple[FSRSensor, float]:
    if kind == "taxel_noise":
        return FSRSensor(noise_std=float(level)), 0.0
    if kind in ("dead_taxels", "dead_taxels_repaired"):
        return FSRSensor(dead_taxel_rate=float(level)), 0.0
    return FSRSensor(), float(level)


def _view(kind: str) -> str:
    """Which frames a noise kind's models read: "repaired" or "raw" (as touched)."""
    return "repaired" if kind.endswith("_repaired") else "raw"


def noise_rows(ctx: Context, objects) -> list[dict]:
    """Accuracy rows {pose, kind, level, strategy, classifier, accuracy} for every noise kind and level (0
    included): each fold's models of the unseen-objects part (which must have run) read that fold's test objects in
    each pose of :data:`NOISE_POSES`. Each (pose, strategy) is a :class:`NoiseJob` on the run's workers; the rows
    come in pose, then strategy order.

    Args:
        objects: the unseen-objects part's objects (the same list, so the folds are the same).
    """
    sizes = ctx.sizes
    # loaded here and sent with the jobs: a worker may not know a model's class until it unpickles one
    estimators = tuple({name: _on_every_core(load_model(fold_folder(ctx, "unseen", sizes.strategies, i)
                                                        / f"{name}{SUFFIX}"))
                        for name in sizes.unseen_classifiers} for i in range(sizes.unseen_folds))
    jobs = []
    for pose in NOISE_POSES:
        ds, _, test_ds, _ = pose_stores(ctx, objects, pose, sizes.strategies, sizes.unseen_contours,
                                        sizes.unseen_train_contours)
        posed = tuple(objects if pose == "upright" else any_pose(objects, ctx.seed))
        jobs += [NoiseJob(str(ctx.out), ctx.seed, sizes, posed, pose, strategy, str(ds.path), str(test_ds.path),
                          estimators) for strategy in sizes.strategies]
    return [row for rows in ctx.run_jobs(jobs, "noise", "setting") for row in rows]


@dataclass(frozen=True)
class NoiseJob:
    """The rows of :func:`noise_rows` for one pose and strategy, a job for
    :func:`fusion.experiments.parallel.run_jobs`: ``objects`` in that pose, the unseen-objects part's training store
    (its folds) and test store (its interest points) by path, the report folder ``out`` (the touched batches' cache)
    and ``estimators``, each fold's fitted models by name."""

    out: str
    seed: int
    sizes: Sizes
    objects: tuple
    pose: str
    strategy: str
    train_store: str
    test_store: str
    estimators: tuple

    def run(self) -> list[dict]:
        from tactile.dataset import open_dataset

        ctx = Context(Path(self.out), self.seed, self.sizes, {}, progress=False)
        sizes, pose, strategy = self.sizes, self.pose, self.strategy
        ds = open_dataset(self.train_store)
        test_ds = ds if self.test_store == self.train_store else open_dataset(self.test_store)
        levels = [("clean", 0.0)] + [(k, float(v)) for k, vs in sizes.noise_levels.items() for v in vs]
        models = {m.name: m for m in load_models(list(self.objects))}
        class_names = list(ds.class_names)
        folds = ds.kfold_by_object(sizes.unseen_folds, seed=ctx.seed, index=ds.indices(strategy))
        fold_objects = [[models[ds.object_names[o]] for o in np.unique(ds.object_ids[test])] for _, test in folds]
        estimators = self.estimators
        attention = _attention(test_ds, list(models.values()), strategy, ctx.seed)
        cleans: dict[int, tuple] = {}  # per fold: the clean batch and its seeds, read once for every level
        rows = []
        for kind, level in levels:
            kinds = list(sizes.noise_levels) if kind == "clean" else [kind]  # clean is level 0 of every kind
            sensor, jitter = _sensor_and_jitter(kind, level)
            preds: dict[tuple[str, str], list] = {}
            for i, test_models in enumerate(fold_objects):
                if i not in cleans:
                    cleans[i] = _touched(ctx, test_models, class_names, pose, strategy, "clean", 0.0, FSRSensor(),
                                         0.0, attention)
                batch = _noisy_batch(ctx, test_models, class_names, pose, strategy, kind, level, sensor, jitter,
                                     attention, clean=cleans[i])
                inputs = _inputs(batch, sensor, kinds)
                for name, estimator in estimators[i].items():
                    for view, data in inputs.items():
                        preds.setdefault((name, view), []).append(predict(estimator, data))
            for name in sizes.unseen_classifiers:
                acc = {view: score(Predictions.concatenate(p), by="object", seed=ctx.seed)
                       for (n, view), p in preds.items() if n == name}
                for k in kinds:
                    rows.append({"pose": pose, "kind": k, "level": level, "strategy": strategy,
                                 "classifier": DISPLAY.get(name, name), "name": name,
                                 "accuracy": acc[_view(k)].to_dict()})
        return rows

    def cost(self) -> float:
        """Guided-like strategies cost more: each object's pair order cuts every pair of interest points first."""
        return 2.0 if METHODS[self.strategy] else 1.0

    def __str__(self) -> str:
        return f"noise rows of {self.strategy} contours, {self.pose}"


def _noisy_batch(ctx: Context, models: list, class_names: list[str], pose: str, strategy: str, kind: str,
                 level: float, sensor: FSRSensor, jitter: float, attention,
                 clean: tuple | None = None) -> SequenceBatch:
    """The test objects touched with one noise kind and level (its ``sensor`` and pose ``jitter``, mm).

    Read-out noise (taxel noise, dead taxels; jitter 0) re-reads the clean batch's frames with each sequence's own
    seed (:meth:`FSRSensor.reread`: the frames touching again would give, bit for bit, without a ray); the clean
    and jittered batches are touched and cached under ``noise/``. ``clean``: the clean (batch, seeds) of these
    models when the caller holds them already."""
    # Re-reading is exact only for the clean pad's geometry: no jitter and every setting but the read-out's default.
    readout_only = jitter == 0 and replace(sensor, noise_std=0.0, dead_taxel_rate=0.0) == FSRSensor()
    if kind == "clean" or readout_only:
        if clean is None:
            clean = _touched(ctx, models, class_names, pose, strategy, "clean", 0.0, FSRSensor(), 0.0, attention)
        clean, seeds = clean
        if kind == "clean":
            return clean
        frames = np.stack([sensor.reread(f, int(s)) for f, s in zip(clean.frames, seeds)])
        return replace(clean, frames=frames, sensor_spec=sensor.spec())
    return _touched(ctx, models, class_names, pose, strategy, kind, level, sensor, jitter, attention)[0]


def _touched(ctx: Context, models: list, class_names: list[str], pose: str, strategy: str, kind: str,
             level: float, sensor: FSRSensor, jitter: float, attention) -> tuple[SequenceBatch, np.ndarray]:
    """The test objects touched with ``sensor`` and ``jitter`` and each sequence's read-out seed, cached."""
    sizes = ctx.sizes
    names = [m.name for m in models]
    key = {"objects": names, "pose": pose, "strategy": strategy, "kind": kind, "level": level,
           "contours": sizes.noise_contours, "seed": ctx.seed + TEST_SEED_OFFSET, "sensor": sensor.spec()}
    path = ctx.path("noise", f"{pose.replace(' ', '')}-{strategy}-{kind}-{level:g}-{digest(names)}.npz")
    found = load_batch_with_seeds(path, key)
    if found is None:
        seeds: list[int] = []
        batch = touch_objects(models, class_names, strategy, sizes.noise_contours, sensor=sensor,
                              seed=ctx.seed + TEST_SEED_OFFSET, jitter_mm=jitter, attention=attention,
                              progress=ctx.progress, noise_seeds=seeds)
        save_batch(batch, path, key, noise_seeds=seeds)
        found = batch, np.asarray(seeds, dtype=np.int64)
    return found


def _inputs(batch: SequenceBatch, sensor: FSRSensor, kinds: list[str]) -> dict[str, SequenceBatch]:
    """The frames the models of ``kinds`` read: as touched ("raw") and/or repaired, each made once."""
    views = {_view(k) for k in kinds}
    inputs = {"raw": batch} if "raw" in views else {}
    if "repaired" in views:
        inputs["repaired"] = replace(batch, frames=repair_dead_taxels(batch.frames, sensor))
    return inputs


__all__ = ["NOISE_POSES", "TEST_SEED_OFFSET", "NoiseJob", "noise_rows"]
