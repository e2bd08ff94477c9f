"""Calibration and open-set experiments: calibrated posteriors at K touches, and objects of classes never trained on.

``calibration``: grouped k-fold by object (the unseen-objects folds), one strategy; each fold's model is calibrated
on its training objects only (:func:`fusion.openset.calibrate`, inner folds by object) and tested on the fold's
objects in their seeded random poses. ECE (15 bins) at K = 1, 2, 4, 8 before (raw probabilities, log rule), with
temperature and smoothing per touch and the tempered log rule, and after (+ the confidence map fitted for K), 95 %
intervals by bootstrap over objects, the noise floor (the mean ECE a perfectly calibrated predictor with the same
confidences shows on that many decisions), and reliability diagrams.

``openset``: classes rotated out of training: the classes (shuffled, seeded) are dealt to R rotations; rotation r
trains on the other classes' objects outside object fold r, calibrated and thresholded on them only (leaving
classes out inside training), and tests the known classes' objects of fold r and every object of its left-out
classes, all in any pose. Per score (max probability, feature distance, class distance, set distance) and K: AUROC
known vs unknown (interval: bootstrap over objects, known and unknown resampled separately), and for the score the training
folds chose: the share of known objects kept and of unknown ones answered "unknown" at the threshold fitted on
training data, plus the share of unknown rejected at the threshold that keeps 95 % of the *test* known decisions.
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fusion.base import class_indices
from fusion.calibration import ece_interval, ece_noise_floor, plot_reliability, reliability
from fusion.decide import fuse_touches, touch_groups
from fusion.experiments.context import Context
from fusion.experiments.models import (
    DISPLAY,
    Factory,
    calibration_code_version,
    digest,
    load_cached,
    model_record,
    pick,
    save_fitted,
)
from fusion.experiments.parallel import StoreRows, fit_cost
from fusion.experiments.protocol import pose_stores, same_objects
from fusion.experiments.report import pivot
from fusion.modelfile import SUFFIX
from fusion.openset import (
    SCORES,
    auroc,
    calibrate,
    calibrated_fusion,
    group_scores,
    per_touch,
    rejected_share,
    threshold_for,
    threshold_keeping,
)
from perception.errors import DatasetError

log = logging.getLogger(__name__)

BOOTSTRAP = 1000
#: The open-set part's CNNs train with this supervised contrastive weight (``CNNClassifier(contrastive_weight=...)``):
#: it gathers each class on the unit sphere where the distance scores are measured. Chosen before measuring (the
#: literature's order of magnitude, one value tried). Screen (2026-12-07, scripts outside the repository): the 5
#: rotations' final models of the exposed run refitted with it; test AUROC of the distance score at K = 8 per rotation
#: 0.937 / 1.000 / 0.798 / 0.994 / 0.958 -> 0.970 / 1.000 / 0.864 / 1.000 / 0.970; the part itself then rejected
#: 81.8 % of the unknown objects at K = 8 against 75.1 % (README). The calibration part keeps the plain CNNs: its ECE
#: is that of the classifiers every other part uses.
OPENSET_CONTRASTIVE = 0.5


def class_index(model, batch) -> np.ndarray:
    """(S,) each sequence's class as an index into ``model.classes_``."""
    return class_indices(model.classes_, np.asarray(batch.class_names, dtype=object)[batch.labels])


#: The calibration part's variants: label -> how K touches' uncalibrated probabilities are fused.
VARIANTS = {
    "before (raw, log rule)": lambda state, raw: fuse_touches(raw, "log"),
    "temperature + smoothing, tempered rule": lambda state, raw: calibrated_fusion(state, raw, maps=False),
    "after (+ confidence map for K)": lambda state, raw: calibrated_fusion(state, raw),
}


@dataclass(frozen=True)
class CalibrationJob:
    """``factory()`` fitted on the rows ``train`` and calibrated there (:func:`fusion.openset.calibrate` with
    ``options``): a job for :func:`fusion.experiments.parallel.run_jobs`. With a ``path``, the calibrated model is
    saved there with its record (the classifier, the store's data (``data``: the digest of the store's record, so that
    a report folder moved elsewhere still finds it), the rows, the options, the calibration code) and a re-run with
    the same record loads it: an interrupted part keeps the calibrations it finished. ``keep=False`` (with a
    ``path``) returns None instead of the model: a pool that only makes the models for later does not send them
    back."""

    factory: Factory
    train: StoreRows
    options: dict
    path: str | None = None
    data: str = ""
    keep: bool = True

    def run(self):
        if self.path is None:
            return calibrate(self.factory(), self.train(), **self.options)
        path = Path(self.path)
        record = model_record(self.factory, {"store": self.data or self.train.path, "train": digest(self.train.index),
                                             "options": self.options, "calibration_code": calibration_code_version()})
        cached = load_cached(path, record)
        if cached is not None:
            if getattr(cached[0], "calibration_", None) is not None:
                return cached[0] if self.keep else None
            log.warning("cached calibration %s holds no calibration; calibrating again", path)
        start = time.perf_counter()
        model = calibrate(self.factory(), self.train(), **self.options)
        save_fitted(model, time.perf_counter() - start, path, record)
        return model if self.keep else None

    def cost(self) -> float:
        return fit_cost(self.factory, self.train)

    def __str__(self) -> str:
        return f"calibrating {type(self.factory()).__name__} on {len(self.train.index)} sequences of {self.train.path}"


#: Calibration folds of the parts' :func:`fusion.openset.calibrate` calls, where every class has that many training
#: objects (fewer in a small run: ``--quick`` trains on 2 or 3 objects of a class).
CALIBRATION_FOLDS = 3


def calibration_folds(ds, trains, part: str) -> int:
    """:data:`CALIBRATION_FOLDS`, or the fewest objects of one class in any of the training rows ``trains`` of the
    opened store ``ds`` if that is smaller.

    Raises:
        DatasetError: a training set holds a single object of some class (calibration needs two folds).
    """
    counts = [int(np.unique(ds.object_ids[train][ds.labels[train] == c]).size)
              for train in trains for c in np.unique(ds.labels[train])]
    if not counts:
        raise DatasetError(f"{ds.path}: the {part} part has no training rows")
    fewest = min(counts)
    if fewest < 2:
        raise DatasetError(f"{ds.path}: the {part} part needs at least 2 training objects of every class in each "
                           "fold; give more objects per class")
    return min(CALIBRATION_FOLDS, fewest)


def calibrate_parts(ctx: Context, objects, parts) -> None:
    """Make every calibrated model the named ``parts`` ("calibration", "openset") need, side by side in one pool
    (saved where the parts load them): part by part, a worker idles while the last calibration of each part runs
    (on 2 workers: the 3 of the calibration part, each 4 fits, then the 5 of the open-set part, each 8 fits)."""
    jobs = []
    if "calibration" in parts:
        jobs += _calibration_plan(ctx, objects)[-1]
    if "openset" in parts:
        jobs += _openset_plan(ctx, objects)[-1]
    ctx.run_jobs([replace(job, keep=False) for job in jobs])


def _calibration_plan(ctx: Context, objects) -> tuple:
    """(training store, test store, grouped folds, classifier factories, the calibration jobs in
    fold-then-classifier order) of the calibration part."""
    sizes = ctx.sizes
    ds, record, test_ds, _ = pose_stores(ctx, objects, "any pose", sizes.strategies, sizes.unseen_contours)
    folds = ds.kfold_by_object(sizes.unseen_folds, seed=ctx.seed, index=ds.indices(sizes.calibration_strategy))
    factories, jobs = _jobs(ctx, ds, record, [train for train, _ in folds], "calibration", "fold", open_set=False)
    return ds, test_ds, folds, factories, jobs


def exposed(ctx: Context, factories: dict) -> dict:
    """``factories`` with each CNN's trained with outlier exposure (:class:`fusion.cnn.CNNClassifier`'s ``outliers``)
    on the touches of ``ctx.outliers`` (each in its seeded random pose, the part's strategy and contour count, in a
    store of the report folder, whose name carries its record's digest); as they are without outliers."""
    from fusion.cnn import CNNClassifier
    from fusion.experiments.data import any_pose

    cnns = [name for name, factory in factories.items() if isinstance(factory(), CNNClassifier)]
    if not ctx.outliers or not cnns:  # no store is made that no model reads
        return factories
    sizes = ctx.sizes
    store, _ = ctx.store(any_pose(ctx.outliers, ctx.seed), strategies=(sizes.calibration_strategy,),
                         contours=sizes.unseen_contours)
    return {name: functools.partial(factory, outliers=str(store.path)) if name in cnns else factory
            for name, factory in factories.items()}


def contrastive(factories: dict, weight: float) -> dict:
    """``factories`` with each CNN's trained with the supervised contrastive term of weight ``weight`` (as they are
    for 0)."""
    from fusion.cnn import CNNClassifier

    if weight == 0:
        return factories
    return {name: functools.partial(factory, contrastive_weight=weight) if isinstance(factory(), CNNClassifier)
            else factory for name, factory in factories.items()}


def _jobs(ctx: Context, ds, record: dict, trains: list, part: str, label: str, contrastive_weight: float = 0.0,
          **options) -> tuple:
    """(classifier factories, a :class:`CalibrationJob` per training rows and classifier, saved as
    ``<part>/<label><i>-<classifier>.vtm``) of a part on the store ``ds`` made with ``record``; the CNNs with
    ``contrastive_weight`` (:func:`contrastive`)."""
    factories = contrastive(exposed(ctx, pick(ctx.classifiers, ctx.sizes.calibration_classifiers)), contrastive_weight)
    options |= {"max_touches": max(ctx.sizes.touches), "random_state": ctx.seed,
                "cv": calibration_folds(ds, trains, part)}
    jobs = [CalibrationJob(factory, StoreRows(str(ds.path), train), options,
                           str(ctx.path(part, f"{label}{i + 1}-{name}{SUFFIX}")), digest(record))
            for i, train in enumerate(trains) for name, factory in factories.items()]
    return factories, jobs


def calibration_part(ctx: Context, objects) -> dict:
    """ECE rows and reliability figures (module docstring); returns {"rows", "fits", "figures"}."""
    sizes = ctx.sizes
    strategy = sizes.calibration_strategy
    ds, test_ds, folds, factories, jobs = _calibration_plan(ctx, objects)
    models = iter(ctx.run_jobs(jobs))
    collected: dict[str, list] = {}
    fits = []
    for i, (_, test) in enumerate(folds):
        batch = test_ds.load(same_objects(ds, test, test_ds, strategy))
        for name in factories:
            model = next(models)
            state = model.calibration_
            collected.setdefault(name, []).append({
                "raw": model.predict_proba_uncalibrated(batch), "y": class_index(model, batch), "state": state,
                "obj": np.asarray(batch.object_names, dtype=object)[batch.object_ids]})
            fits.append({"classifier": DISPLAY.get(name, name), "fold": i + 1,
                         "temperature": round(state["temperature"], 4), "smoothing": round(state["smoothing"], 4),
                         "dependence": round(state["dependence"], 4)})
    rows, figures = [], []
    for name, parts in collected.items():
        curves = {}
        for k in sizes.touches:
            fused = {label: [] for label in VARIANTS}
            ys, objs = [], []
            for part in parts:  # each fold's decisions with that fold's calibration (groups never span folds)
                names, ids = np.unique(part["obj"], return_inverse=True)
                groups = touch_groups(ids, k, seed=ctx.seed)
                for label, fuse in VARIANTS.items():
                    fused[label].append(fuse(part["state"], part["raw"][groups]))
                ys.append(part["y"][groups[:, 0]])
                objs.append(names[ids[groups[:, 0]]])
            y, obj = np.concatenate(ys), np.concatenate(objs)
            for label in VARIANTS:
                f = np.concatenate(fused[label])
                e = ece_interval(f, y, obj, n_boot=BOOTSTRAP, seed=ctx.seed)
                rows.append({"classifier": DISPLAY.get(name, name), "name": name, "k": int(k), "variant": label, **e,
                             "noise_floor": ece_noise_floor(f.max(axis=1), seed=ctx.seed),
                             "accuracy": float(np.mean(f.argmax(axis=1) == y)),
                             "mean_confidence": float(f.max(axis=1).mean())})
                if k in (1, max(sizes.touches)) and label != "temperature + smoothing, tempered rule":
                    curves[f"K={k}, {label.split(' (')[0]}"] = reliability(f, y)
        file = f"reliability_{name}.png"
        plot_reliability(curves, ctx.path(file), title=f"{DISPLAY.get(name, name)}, {strategy}, unseen objects in "
                                                       "any pose")
        figures.append(file)
    return {"rows": rows, "fits": fits, "figures": figures, "strategy": strategy}


def _objects_bootstrap(known_scores, known_obj, unknown_scores, unknown_obj, stat, seed: int) -> tuple[float, float]:
    """95 % percentile interval of ``stat(known, unknown)``, resampling known and unknown objects separately."""
    rng = np.random.default_rng(seed)
    k_names, k_ids = np.unique(known_obj, return_inverse=True)
    u_names, u_ids = np.unique(unknown_obj, return_inverse=True)
    k_members = [np.flatnonzero(k_ids == i) for i in range(len(k_names))]
    u_members = [np.flatnonzero(u_ids == i) for i in range(len(u_names))]
    values = []
    for _ in range(BOOTSTRAP):
        ki = np.concatenate([k_members[i] for i in rng.integers(0, len(k_members), len(k_members))])
        ui = np.concatenate([u_members[i] for i in rng.integers(0, len(u_members), len(u_members))])
        values.append(stat(known_scores[ki], unknown_scores[ui]))
    low, high = np.percentile(values, [2.5, 97.5])
    return float(low), float(high)


def _openset_plan(ctx: Context, objects) -> tuple:
    """(test store, classes left out per rotation, (training rows, test rows) per rotation, classifier factories,
    the calibration jobs in rotation-then-classifier order) of the open-set part."""
    sizes = ctx.sizes
    strategy = sizes.calibration_strategy
    ds, record, test_ds, _ = pose_stores(ctx, objects, "any pose", sizes.strategies, sizes.unseen_contours)
    index = ds.indices(strategy)
    n_rot = sizes.openset_rotations
    folds = ds.kfold_by_object(n_rot, seed=ctx.seed, index=index)
    class_names = np.asarray(ds.class_names, dtype=object)
    rng = np.random.default_rng(ctx.seed)
    order = rng.permutation(len(class_names))
    left_out = [sorted(class_names[order[r::n_rot]].tolist()) for r in range(n_rot)]
    labels_all = class_names[ds.labels]
    splits = []  # (training rows, test rows of the test store) of each rotation
    for r, (_, fold_test) in enumerate(folds):
        unknown_idx = index[np.isin(labels_all[index], left_out[r])]
        known_test = fold_test[~np.isin(labels_all[fold_test], left_out[r])]
        train = np.setdiff1d(index[~np.isin(labels_all[index], left_out[r])], known_test)
        splits.append((train, same_objects(ds, np.union1d(known_test, unknown_idx), test_ds, strategy)))
    factories, jobs = _jobs(ctx, ds, record, [train for train, _ in splits], "openset", "rotation",
                            contrastive_weight=OPENSET_CONTRASTIVE)
    return test_ds, left_out, splits, factories, jobs


def openset_part(ctx: Context, objects) -> dict:
    """Open-set rows (module docstring); returns {"rows", "rotations"}."""
    sizes = ctx.sizes
    strategy = sizes.calibration_strategy
    ks = list(sizes.touches)
    test_ds, left_out, splits, factories, jobs = _openset_plan(ctx, objects)
    models = iter(ctx.run_jobs(jobs))
    pooled: dict = {}
    rotations = []
    for r, (_, test) in enumerate(splits):
        batch = test_ds.load(test)
        for name in factories:
            model = next(models)
            proba, distances, by_object = per_touch(model, batch)
            label = np.asarray(batch.class_names, dtype=object)[batch.labels]
            is_unknown = np.isin(label, left_out[r])
            obj = np.asarray(batch.object_names, dtype=object)[batch.object_ids]
            _, ids = np.unique(obj, return_inverse=True)
            cal = model.calibration_
            rotations.append({"rotation": r + 1, "classifier": DISPLAY.get(name, name), "left_out": left_out[r],
                              "known_test_objects": len(np.unique(obj[~is_unknown])),
                              "unknown_objects": len(np.unique(obj[is_unknown])),
                              "score": cal["score"], "temperature": round(cal["temperature"], 4),
                              "smoothing": round(cal["smoothing"], 4),
                              "dependence": round(cal["dependence"], 4), "inner_auroc": cal["inner_auroc"]})
            for k in ks:
                groups = touch_groups(ids, k, seed=ctx.seed)
                s = group_scores(proba, groups, cal, distances, by_object)
                unknown_g = is_unknown[groups[:, 0]]
                p = pooled.setdefault((name, k), {"unknown": [], "obj": [], "label": [], "chosen": [], "threshold": [],
                                                  **{n: [] for n in SCORES}})
                p["unknown"].append(unknown_g)
                p["label"].append(label[groups[:, 0]])
                p["obj"].append(np.array([f"{r}:{o}" for o in obj[groups[:, 0]]], dtype=object))
                p["chosen"].append(s[cal["score"]])
                p["threshold"].append(np.full(len(groups), threshold_for(model, k)))
                for n in SCORES:
                    p[n].append(s.get(n, np.full(len(groups), np.nan)))
    rows = []
    for (name, k), p in pooled.items():
        unknown = np.concatenate(p["unknown"])
        obj = np.concatenate(p["obj"])
        for n in (*SCORES, "chosen"):
            scores = np.concatenate(p[n])
            if not np.isfinite(scores).all():
                continue
            known_s, unknown_s = scores[~unknown], scores[unknown]
            value = auroc(known_s, unknown_s)
            low, high = _objects_bootstrap(known_s, obj[~unknown], unknown_s, obj[unknown], auroc, ctx.seed)
            row = {"classifier": DISPLAY.get(name, name), "name": name, "k": int(k), "score": n,
                   "auroc": value, "auroc_low": low, "auroc_high": high,
                   "n_known": int((~unknown).sum()), "n_unknown": int(unknown.sum())}
            oracle = threshold_keeping(known_s, 0.95)
            row["rejected_at_test_95"] = rejected_share(unknown_s, oracle)
            if n == "chosen":
                thresholds = np.concatenate(p["threshold"])
                known_kept = float(np.mean(known_s >= thresholds[~unknown]))
                below = unknown_s < thresholds[unknown]  # answered "unknown"
                rejected = float(np.mean(below))
                row |= {"known_kept": known_kept, "unknown_rejected": rejected}
                lo, hi = _objects_bootstrap(known_s - thresholds[~unknown], obj[~unknown],
                                            unknown_s - thresholds[unknown], obj[unknown],
                                            lambda a, b: float(np.mean(b < 0)), ctx.seed)
                row |= {"unknown_rejected_low": lo, "unknown_rejected_high": hi}
                lo, hi = _objects_bootstrap(known_s - thresholds[~unknown], obj[~unknown],
                                            unknown_s - thresholds[unknown], obj[unknown],
                                            lambda a, b: float(np.mean(a >= 0)), ctx.seed)
                row |= {"known_kept_low": lo, "known_kept_high": hi}
                # which unknown classes pass for known ones (e.g. a bird for an airplane)
                unknown_label = np.concatenate(p["label"])[unknown]
                row["rejected_by_class"] = {str(c): float(np.mean(below[unknown_label == c]))
                                            for c in sorted(set(unknown_label))}
            rows.append(row)
    return {"rows": rows, "rotations": rotations, "left_out": left_out, "strategy": strategy}


def rejected_by_class_lines(rows: list[dict]) -> list[str]:
    """One line per classifier: the share of each left-out class's objects answered "unknown" at the thresholds
    fitted on training data, at the largest K (the chosen score)."""
    lines = []
    for name in dict.fromkeys(r["classifier"] for r in rows):
        chosen = [r for r in rows if r["classifier"] == name and "rejected_by_class" in r]
        if chosen:
            last = max(chosen, key=lambda r: r["k"])
            shares = ", ".join(f"{c} {100 * v:.0f} %" for c, v in last["rejected_by_class"].items())
            lines.append(f"{name}, K = {last['k']}, unknown answered 'unknown' by left-out class: {shares}.")
    return lines


def calibration_table(rows: list[dict]) -> list[dict]:
    """Markdown rows: classifier, variant, then ECE [interval] (accuracy, mean confidence) per K."""
    return pivot(rows, ("classifier", "variant"), _ece_cell)


def openset_table(rows: list[dict]) -> list[dict]:
    """Markdown rows: classifier, score, then AUROC [interval] per K; the chosen score also shows the shares."""
    return pivot(rows, ("classifier", "score"), _auroc_cell)


def _ece_cell(h: dict) -> str:
    return (f"{h['ece']:.3f} [{h['low']:.3f}, {h['high']:.3f}] (floor {h['noise_floor']:.3f}; "
            f"acc {100 * h['accuracy']:.0f} %, conf {100 * h['mean_confidence']:.0f} %)")


def _auroc_cell(h: dict) -> str:
    text = f"{h['auroc']:.3f} [{h['auroc_low']:.3f}, {h['auroc_high']:.3f}]"
    if "unknown_rejected" in h:
        text += (f"; kept {100 * h['known_kept']:.0f} %, rejected {100 * h['unknown_rejected']:.0f} % "
                 f"[{100 * h['unknown_rejected_low']:.0f}, {100 * h['unknown_rejected_high']:.0f}]")
    return text + f"; @95 % test-known {100 * h['rejected_at_test_95']:.0f} %"


__all__ = ["VARIANTS", "calibration_part", "calibration_table", "class_index", "openset_part", "openset_table",
           "rejected_by_class_lines"]
