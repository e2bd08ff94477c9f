"""The paper's protocol (80/20 by sequence) and unseen objects (grouped k-fold by object), for each strategy
of the run's sizes, and K touches per decision on their test predictions.

Models and predictions are cached under ``models/<part>/<strategy>/[fold<i>/]<classifier>.{pkl,json,npz}``.
"""

from __future__ import annotations

import numpy as np

from fusion.evaluate import confusion, plot_confusion
from fusion.experiments.analysis import paired_difference, score, touch_curve
from fusion.experiments.context import Context
from fusion.experiments.data import any_pose, store_record
from fusion.experiments.models import DISPLAY, MODALITY_DISPLAY, Predictions, digest, pick
from fusion.experiments.parallel import FitTask, StoreRows
from perception.errors import DatasetError, InvalidArgumentError


def accuracy_rows(preds: dict[str, dict[str, Predictions]], by: str, seed: int) -> list[dict]:
    """One row per (classifier or CNN modality, strategy): accuracy with interval and times."""
    rows = []
    for strategy, by_clf in preds.items():
        for name, pred in by_clf.items():
            variants = [(DISPLAY.get(name, name), pred)]
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


def paper_dataset(ctx: Context, objects):
    """The paper protocol's dataset (generated, resumed or reused) and its store record."""
    return ctx.store(objects, strategies=ctx.sizes.strategies, contours=ctx.sizes.paper_contours)


def paper_protocol(ctx: Context, objects) -> dict[str, dict[str, Predictions]]:
    """Train every paper classifier on 80 % of each strategy's sequences and predict the other 20 %.

    Returns predictions[strategy][classifier name]; models go to ``models/paper/<strategy>/``.
    """
    sizes = ctx.sizes
    ds, record = paper_dataset(ctx, objects)
    tasks: dict[tuple[str, str], FitTask] = {}
    for strategy in sizes.strategies:
        train, test = ds.split_by_sequence(sizes.test_fraction, seed=ctx.seed, index=ds.indices(strategy))
        train_record = {"part": "paper", "store": digest(record), "strategy": strategy, "train": digest(train)}
        test_record = {"tag": "test", "test": digest(test)}
        for name, factory in pick(ctx.classifiers, sizes.paper_classifiers).items():
            tasks[strategy, name] = FitTask(name, factory, StoreRows(str(ds.path), train), StoreRows(str(ds.path), test),
                                            ctx.path("models", "paper", strategy), train_record, test_record)
    preds: dict[str, dict[str, Predictions]] = {}
    for (strategy, name), pred in zip(tasks, ctx.run(list(tasks.values())), strict=True):
        preds.setdefault(strategy, {})[name] = pred
    return preds


#: Poses the unseen-objects part tests in: as stored (upright) and each object turned by its own seeded,
#: uniformly random rotation applied to the raw mesh before loading (see ``data.any_pose``).
POSES = ("upright", "any pose")


def unseen_objects(ctx: Context, objects, poses=POSES) -> dict[str, dict[str, dict[str, Predictions]]]:
    """Grouped k-fold by object (each fold's test objects never seen in training), both strategies.

    One model per fold and classifier, trained on the training objects' contours of every strategy together
    (the robot's model learns from all it simulated); guided and blind then differ only in which contours
    touch the test objects, so their paired difference measures the choice of touch alone. Models train on the
    objects as stored; the ``"any pose"`` pose tests each fold's models on the same test objects turned by their
    random rotations (a robot never sees a data set's pose), so the poses are paired object by object.

    Returns out-of-fold predictions[pose][strategy][classifier name], each pose covering every test object once.

    Raises:
        InvalidArgumentError: an unknown pose.
    """
    sizes = ctx.sizes
    stores = {pose: pose_stores(ctx, objects, pose, sizes.strategies, sizes.unseen_contours,
                                sizes.unseen_train_contours) for pose in poses}
    classifiers = pick(ctx.classifiers, sizes.unseen_classifiers)
    return grouped_kfold(ctx, "unseen", stores, sizes.strategies, classifiers, sizes.unseen_folds, pooled=True)


def pose_stores(ctx: Context, objects, pose: str, strategies, contours: int, train_contours: int | None = None
                ) -> tuple:
    """(training store, its record, test store, its record): the objects as stored with ``train_contours``
    contours each (None: ``contours``) for training, and for testing the objects with ``contours`` each, as
    stored (``"upright"``: the training store itself when the counts agree) or each in its seeded random pose
    (``"any pose"``).

    Raises:
        InvalidArgumentError: an unknown pose.
    """
    if pose not in POSES:
        raise InvalidArgumentError(f"unknown pose {pose!r}; choose one of {', '.join(POSES)}")
    train_contours = contours if train_contours is None else train_contours
    train = ctx.store(objects, strategies=strategies, contours=train_contours)
    if pose == "upright" and train_contours == contours:
        return (*train, *train)
    tested = objects if pose == "upright" else any_pose(objects, ctx.seed)
    return (*train, *ctx.store(tested, strategies=strategies, contours=contours))


def grouped_kfold(ctx: Context, part: str, stores: dict[str, tuple], strategies, classifiers: dict, n_folds: int, *,
                  pooled: bool = False) -> dict[str, dict[str, dict[str, Predictions]]]:
    """Out-of-fold predictions {pose: {strategy: {classifier name: Predictions}}}: ``n_folds`` seeded folds by
    object of the training store; each fold's models predict that fold's test objects read from each pose's test
    store (:func:`pose_stores`, by pose name: the same objects, maybe in another pose or with other contours; the
    pose names the cached predictions). Every pose's stores must share one training store; all fits and
    predictions run in one batch, so the test poses never wait for each other's fits.

    ``pooled=False``: a model per strategy, trained on that strategy's contours (cached under
    ``models/<part>/<strategy>/fold<i>/``); ``pooled=True``: one model per fold, trained on the contours of every
    strategy in ``strategies`` (cached under ``models/<part>/<strategy>+<strategy>.../fold<i>/``), predicting each
    strategy's test contours. The folds are the same either way (the same objects, dealt by class).

    Raises:
        InvalidArgumentError: poses whose stores train on different stores.
    """
    if len({str(s[0].path) for s in stores.values()}) > 1:
        raise InvalidArgumentError(f"{part}: the poses {list(stores)} must share one training store")
    groups = [(s,) for s in strategies] if not pooled else [tuple(strategies)]
    tasks = {(pose, *key): task for pose, pose_store in stores.items() for group in groups
             for key, task in kfold_tasks(ctx, part, pose_store, group, classifiers, n_folds, pose).items()}
    parts: dict[tuple[str, str, str], list[Predictions]] = {}
    for (pose, strategy, name, _), pred in zip(tasks, ctx.run(list(tasks.values())), strict=True):
        parts.setdefault((pose, strategy, name), []).append(pred)
    return {pose: {s: {name: Predictions.concatenate(parts[(pose, s, name)]) for name in classifiers}
                   for s in strategies} for pose in stores}


def fold_folder(ctx: Context, part: str, strategies, fold: int):
    """Where fold ``fold`` (0-based) of ``part`` caches the models trained on the contours of ``strategies``."""
    return ctx.path("models", part, "+".join(strategies), f"fold{fold + 1}")


def pooled_folds(ctx: Context, ds, strategies, n_folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ``n_folds`` grouped folds by object (:meth:`~tactile.dataset.TactileDataset.kfold_by_object`, the run's
    seed) over the contours of every strategy in ``strategies``: [(train, test)] row indices of ``ds``."""
    index = np.sort(np.concatenate([ds.indices(s) for s in strategies]))
    return ds.kfold_by_object(n_folds, seed=ctx.seed, index=index)


def kfold_tasks(ctx: Context, part: str, stores: tuple, strategies: tuple, classifiers: dict, n_folds: int,
                pose: str) -> dict[tuple[str, str, int], FitTask]:
    """The fits of :func:`grouped_kfold` with models trained on the contours of all of ``strategies`` together
    (:func:`pooled_folds`), by (strategy, classifier name, fold). ``stores``: (training store, its record, test
    store, its record), as :func:`pose_stores` gives them."""
    ds, record, test_ds, test_store = stores
    folds = pooled_folds(ctx, ds, strategies, n_folds)
    pooled = len(strategies) > 1
    tasks: dict[tuple[str, str, int], FitTask] = {}
    for i, (train, test_all) in enumerate(folds):
        train_record = {"part": part, "store": digest(record), "strategy": "+".join(strategies), "train": digest(train)}
        folder = fold_folder(ctx, part, strategies, i)
        for strategy in strategies:
            test = test_all[ds.sequence_strategies[test_all] == strategy]
            test = test if test_ds is ds else same_objects(ds, test, test_ds, strategy)
            tag = "test" if pose == "upright" else "anypose"
            test_record = {"tag": f"{strategy}-{tag}" if pooled else tag, "test": digest(test)}
            if test_ds is not ds:
                test_record["store"] = digest(test_store)
            for name, factory in classifiers.items():
                tasks[strategy, name, i] = FitTask(name, factory, StoreRows(str(ds.path), train),
                                                   StoreRows(str(test_ds.path), test), folder, train_record, test_record)
    return tasks


def same_objects(ds, index: np.ndarray, other, strategy: str) -> np.ndarray:
    """Indices into the store ``other`` of the ``strategy`` sequences of the objects that ``index`` selects in
    ``ds`` (matched by object name: the same objects in another pose).

    Raises:
        DatasetError: an object of ``index`` is missing from ``other`` (e.g. it failed to generate there).
    """
    names = {ds.object_names[i] for i in np.unique(ds.object_ids[index])}
    missing = names - set(other.object_names)
    if missing:
        raise DatasetError(f"{other.path}: objects {sorted(missing)[:3]} are missing; cannot pair the poses")
    wanted = np.isin(np.asarray(other.object_names, dtype=object)[other.object_ids], list(names))
    return np.flatnonzero(wanted & (other.sequence_strategies == strategy)).astype(np.int64)


def _paired_rows(row: dict, name: str, a: Predictions, b: Predictions, ks, seed: int) -> list[dict]:
    """``row`` + the paired difference a - b (:func:`fusion.experiments.analysis.paired_difference`, log rule)
    for every K that each object of both has enough sequences for."""
    usable = [k for k in ks if k <= min(_min_per_object(a), _min_per_object(b))]
    return [{**row, "classifier": DISPLAY.get(name, name), "name": name, "k": k,
             **paired_difference(a, b, k, seed=seed)} for k in usable]


def strategy_differences(by_pose: dict[str, dict[str, dict[str, Predictions]]], ks, seed: int) -> list[dict]:
    """Guided minus blind accuracy per (pose, classifier, K), paired over the objects both strategies tested.
    Empty unless both strategies ran."""
    return [r for pose, preds in by_pose.items() if {"guided", "blind"} <= set(preds)
            for name in preds["guided"]
            for r in _paired_rows({"pose": pose}, name, preds["guided"][name], preds["blind"][name], ks, seed)]


def pose_differences(by_pose: dict[str, dict[str, dict[str, Predictions]]], ks, seed: int) -> list[dict]:
    """Any-pose minus upright accuracy per (strategy, classifier, K), paired over the test objects."""
    upright, turned = by_pose.get("upright", {}), by_pose.get("any pose", {})
    return [r for strategy, preds in upright.items() for name in preds if name in turned.get(strategy, {})
            for r in _paired_rows({"strategy": strategy}, name, turned[strategy][name], preds[name], ks, seed)]


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


__all__ = [
    "POSES",
    "accuracy_rows",
    "confusion_figures",
    "fold_folder",
    "grouped_kfold",
    "kfold_tasks",
    "paper_dataset",
    "paper_protocol",
    "pooled_folds",
    "pose_stores",
    "same_objects",
    "store_record",
    "touches_rows",
    "unseen_objects",
]
