"""The paper's protocol (80/20 by sequence) and unseen objects (grouped k-fold by object), for each strategy
of the run's sizes, and K touches per decision on their test predictions.

Models and predictions are cached under ``models/<part>/<strategy>/[fold<i>/]<classifier>.{pkl,json,npz}``.
"""

from __future__ import annotations

import logging

import numpy as np

from fusion.evaluate import confusion, plot_confusion
from fusion.experiments.analysis import score, touch_curve
from fusion.experiments.context import Context
from fusion.experiments.data import ensure_store, store_record
from fusion.experiments.models import DISPLAY, MODALITY_DISPLAY, Predictions, digest, pick, train_and_predict

log = logging.getLogger(__name__)

STRATEGIES = ("guided", "blind")


def accuracy_rows(preds: dict[str, dict[str, Predictions]], by: str, seed: int) -> list[dict]:
    """One row per (classifier or CNN modality, strategy): accuracy with interval and times."""
    rows = []
    for strategy, by_clf in preds.items():
        for name, pred in by_clf.items():
            variants = [(DISPLAY.get(name, name), pred)]
            if name == "cnn":
                variants += [(MODALITY_DISPLAY[m], pred.modality(m)) for m in MODALITY_DISPLAY if m in pred.modalities]
            for label, p in variants:
                rows.append({"classifier": label, "name": name, "strategy": strategy,
                             "accuracy": score(p, by=by, seed=seed).to_dict(),
                             "fit_seconds": round(pred.fit_seconds, 2),
                             "predict_ms_per_sequence": round(1000 * pred.predict_seconds, 3)})
    return rows


def confusion_figures(ctx: Context, preds: dict[str, dict[str, Predictions]], setting: str) -> list[str]:
    """A confusion-matrix PNG per (strategy, classifier); returns the file names (relative to the report)."""
    names = []
    for strategy, by_clf in preds.items():
        for name, pred in by_clf.items():
            file = f"confusion_{setting}_{strategy}_{name}.png"
            matrix = confusion(pred.labels, pred.predicted, pred.classes)
            plot_confusion(matrix, pred.classes, ctx.path(file),
                           title=f"{DISPLAY.get(name, name)}, {strategy}, {setting.replace('_', ' ')}")
            names.append(file)
    return names


def _loader(ds, train, test):
    """``load("train" | "test")``: the split's batch, read from the store once and only when asked for."""
    cache: dict = {}

    def load(which: str):
        if which not in cache:
            cache[which] = ds.load(train if which == "train" else test)
        return cache[which]

    return load


def paper_dataset(ctx: Context, objects):
    """The paper protocol's dataset (generated, resumed or reused) and its store record."""
    sizes = ctx.sizes
    return ensure_store(objects, ctx.path("stores"), strategies=sizes.strategies, contours=sizes.paper_contours,
                        seed=ctx.seed, workers=ctx.workers, progress=ctx.progress)


def paper_protocol(ctx: Context, objects) -> dict[str, dict[str, Predictions]]:
    """Train every paper classifier on 80 % of each strategy's sequences and predict the other 20 %.

    Returns predictions[strategy][classifier name]; models go to ``models/paper/<strategy>/``.
    """
    sizes = ctx.sizes
    ds, record = paper_dataset(ctx, objects)
    preds: dict[str, dict[str, Predictions]] = {}
    for strategy in sizes.strategies:
        train, test = ds.split_by_sequence(sizes.test_fraction, seed=ctx.seed, index=ds.indices(strategy))
        batch = _loader(ds, train, test)

        train_record = {"part": "paper", "store": digest(record), "strategy": strategy, "train": digest(train)}
        test_record = {"tag": "test", "test": digest(test)}
        preds[strategy] = {}
        for name, factory in pick(ctx.classifiers, sizes.paper_classifiers).items():
            log.info("paper protocol, %s: %s", strategy, name)
            preds[strategy][name] = train_and_predict(
                name, factory, lambda b=batch: b("train"), lambda b=batch: b("test"),
                ctx.path("models", "paper", strategy), train_record, test_record)
    return preds


def unseen_objects(ctx: Context, objects) -> dict[str, dict[str, Predictions]]:
    """Grouped k-fold by object (each fold's test objects never seen in training), both strategies.

    Returns out-of-fold predictions[strategy][classifier name] covering every sequence once.
    """
    sizes = ctx.sizes
    ds, record = ensure_store(objects, ctx.path("stores"), strategies=sizes.strategies,
                      contours=sizes.unseen_contours, seed=ctx.seed, workers=ctx.workers, progress=ctx.progress)
    preds: dict[str, dict[str, Predictions]] = {}
    for strategy in sizes.strategies:
        folds = ds.kfold_by_object(sizes.unseen_folds, seed=ctx.seed, index=ds.indices(strategy))
        parts: dict[str, list[Predictions]] = {}
        for i, (train, test) in enumerate(folds):
            batch = _loader(ds, train, test)

            train_record = {"part": "unseen", "store": digest(record), "strategy": strategy, "train": digest(train)}
            for name, factory in pick(ctx.classifiers, sizes.unseen_classifiers).items():
                log.info("unseen objects, %s, fold %d: %s", strategy, i + 1, name)
                parts.setdefault(name, []).append(train_and_predict(
                    name, factory, lambda b=batch: b("train"), lambda b=batch: b("test"),
                    ctx.path("models", "unseen", strategy, f"fold{i + 1}"), train_record,
                    {"tag": "test", "test": digest(test)}))
        preds[strategy] = {name: Predictions.concatenate(p) for name, p in parts.items()}
    return preds


def touches_rows(preds: dict[str, dict[str, Predictions]], setting: str, ks, seed: int) -> list[dict]:
    """K-touch accuracy rows (both rules, bootstrap over objects) of every strategy and classifier."""
    rows = []
    for strategy, by_clf in preds.items():
        for name, pred in by_clf.items():
            usable = [k for k in ks if k <= _min_per_object(pred)]
            for row in touch_curve(pred, usable, by="object", seed=seed):
                rows.append({"setting": setting, "strategy": strategy, "classifier": DISPLAY.get(name, name),
                             "name": name, "rule": row["rule"], "k": row["k"],
                             "accuracy": row["accuracy"].to_dict()})
    return rows


def _min_per_object(pred: Predictions) -> int:
    return int(np.bincount(np.unique(pred.object_ids, return_inverse=True)[1]).min())


__all__ = ["STRATEGIES", "accuracy_rows", "confusion_figures", "paper_dataset", "paper_protocol", "store_record",
           "touches_rows", "unseen_objects"]
