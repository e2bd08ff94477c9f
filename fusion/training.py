"""Training a classifier on a dataset store and evaluating it there: what ``visuotactile train`` and ``evaluate`` run.

A model trained by :func:`train_on_store` remembers where (``model.training_``, a :class:`TrainingRecord` as a dict,
saved in its model file), so that :func:`evaluate_on_store` on the same store tests on exactly the sequences
training held out.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fusion.leakage import SPLITS, check_held_out, overlap
from perception.errors import DatasetError, InvalidArgumentError, shown

#: How training holds out test sequences: by sequence (the paper's 80/20), by object (unseen objects), or none.


@dataclass(frozen=True)
class TrainingRecord:
    """Where a model was trained: the store (path and id), the split and its settings, the training size."""

    store: str
    store_id: str
    split: str
    strategy: str | None
    test_fraction: float
    seed: int
    train_sequences: int

    def to_dict(self) -> dict:
        return asdict(self)


def split_indices(dataset, split: str, strategy: str | None, test_fraction: float, seed: int):
    """(train, test) sequence indices of ``dataset`` for ``split`` (test empty for ``"none"``), restricted to
    ``strategy``'s sequences when given. The same arguments give the same indices. ``"sequence"`` keeps the
    sequences of one contour together (a guided plane repeats: the paper's protocol lets copies cross; see
    :func:`_copies_together`).

    Raises:
        InvalidArgumentError: an unknown split.
    """
    if split not in SPLITS:
        raise InvalidArgumentError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    index = dataset.indices(strategy)
    if split == "none":
        return index, index[:0]
    if split == "sequence":
        train, test = dataset.split_by_sequence(test_fraction=test_fraction, seed=seed, index=index)
        return _copies_together(dataset, train, test)
    return dataset.split_by_object(test_fraction=test_fraction, seed=seed, index=index)


def _copies_together(dataset, train: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) with every sequence of one contour (:meth:`~tactile.dataset.TactileDataset.contour_ids`: a guided
    plane touched again) on the side of its first: a test sequence whose copy was trained on is not held out. A store
    without repeated contours splits as before.

    Raises:
        DatasetError: a side left empty.
    """
    both = np.concatenate([train, test])
    order = np.argsort(both, kind="stable")
    both, in_test = both[order], np.concatenate([np.zeros(len(train), bool), np.ones(len(test), bool)])[order]
    ids = dataset.contour_ids(both)
    first = np.full(ids.max() + 1, -1, dtype=np.int64)
    first[ids[::-1]] = np.arange(len(ids))[::-1]  # the position of each contour's first sequence
    in_test = in_test[first[ids]]
    if in_test.all() or not in_test.any():
        raise DatasetError(f"{dataset.path}: split by sequence: every sequence repeats one contour on one side; "
                           "split by object instead (--split object)")
    return both[~in_test], both[in_test]


def train_on_store(store: str | Path, kind: str, out: str | Path, *, cue: str = "invariant", split: str = "sequence",
                   test_fraction: float = 0.2, strategy: str | None = None, random_state: int = 0,
                   calibrated: bool = False, outliers: str | Path | None = None, contrastive: float = 0.0) -> dict:
    """Fit classifier ``kind`` (:func:`fusion.classifiers.make_classifier`) on ``store``'s training part, record
    the :class:`TrainingRecord` as ``model.training_``, save it to ``out`` and score the held-out part.

    With ``calibrated``, :func:`fusion.openset.calibrate` fits it instead: calibrated probabilities and, with at
    least three classes, the "unknown" answer (leave-classes-out folds: up to four), all on the training part
    only; its inner folds train the classifier several more times. ``outliers``: a store of touches of objects of no
    class in ``store``, for the CNN's outlier exposure (:class:`fusion.cnn.CNNClassifier`'s ``outliers``).
    ``contrastive``: the CNN's supervised contrastive weight (``contrastive_weight``; 0: none), which gathers each
    class in the feature space where the "unknown" answer measures its distances.

    Returns:
        {"model", "cue", "out", "train_sequences", "fit_seconds"}, with ``calibrated`` also "calibration"
        ({"temperature", "dependence", "score": the known score or None without a reject option}), and, with a
        held-out part, "test_sequences" and "test_accuracy" (an interval dict), plus "accuracy" (the
        :class:`~fusion.evaluate.Accuracy`).

    Raises:
        InvalidArgumentError: an unknown classifier, cue or split; ``outliers`` or a nonzero ``contrastive`` for a
            classifier other than the CNN, ``outliers`` naming ``store`` itself, or a bad weight. DatasetError: an
            unreadable store; with ``calibrated``, a class with fewer than three training objects.
    """
    from fusion.classifiers import make_classifier
    from fusion.evaluate import accuracy
    from tactile.dataset import open_dataset

    options = {}
    if outliers is not None:
        if kind != "cnn":
            raise InvalidArgumentError(f"outliers: only the cnn model trains with outlier touches, not {kind!r}")
        if Path(outliers).resolve() == Path(store).resolve():
            raise InvalidArgumentError(f"outliers: {outliers} is the training store itself; give a store of objects "
                                       "of no class the model is to know")
        options["outliers"] = str(outliers)
    if isinstance(contrastive, bool) or not isinstance(contrastive, (int, float, np.integer, np.floating)):
        raise InvalidArgumentError(f"contrastive: expected a number (the CNN's weight), got {shown(contrastive)}")
    if contrastive != 0:  # the CNN checks the range itself
        if kind != "cnn":
            raise InvalidArgumentError(f"contrastive: only the cnn model trains with the contrastive term, not {kind!r}")
        options["contrastive_weight"] = contrastive
    dataset = open_dataset(store)
    train, test = split_indices(dataset, split, strategy, test_fraction, random_state)
    model = make_classifier(kind, cue=cue, random_state=random_state, **options)
    start = time.perf_counter()
    training = dataset.load(train)
    if calibrated:
        from fusion.openset import calibrate, objects_per_class

        per_class = objects_per_class(training)
        short = {c: n for c, n in per_class.items() if n < 3}
        if short:
            raise DatasetError(f"{store}: --calibrate needs at least 3 training objects per class (it holds objects "
                               f"out inside the training part); after the {split} split: {short}")
        n_classes = len(per_class)
        model = calibrate(model, training, class_folds=max(2, min(4, n_classes)), open_set=n_classes >= 3,
                          random_state=random_state)
    else:
        model.fit(training)
    fit_s = time.perf_counter() - start
    model.training_ = {**(getattr(model, "training_", None) or {}), **TrainingRecord(  # keeps fit's fingerprints
        str(store), dataset.attrs.get("store_id", ""), split, strategy, test_fraction, random_state, len(train)).to_dict()}
    batch = dataset.load(test) if len(test) else None
    if batch is not None:  # before saving: a model that is not scored on held-out data is not written either
        check_held_out(model, batch, f"{store}: held-out {split} split", by_object=split == "object")
    model.save(out)
    result = {"model": kind, "cue": cue, "out": str(out), "train_sequences": len(train),
              "fit_seconds": round(fit_s, 2)}
    if calibrated:
        state = model.calibration_
        result["calibration"] = {"temperature": round(float(state["temperature"]), 4),
                                 "dependence": round(float(state["dependence"]), 4), "score": state.get("score")}
    if batch is not None:
        truth = np.asarray(batch.class_names, dtype=object)[batch.labels]
        acc = accuracy(truth, model.predict(batch), seed=random_state)
        result.update(test_sequences=len(test), test_accuracy=acc.to_dict(), accuracy=acc)
    return result


def evaluation_indices(model, dataset, store: str | Path, strategy: str | None = None) -> tuple[np.ndarray, str]:
    """The sequences of ``dataset`` to test ``model`` on and what they are: the part training held out when the
    model was trained on this very store (its ``training_``), else all (of ``strategy``)."""
    info = getattr(model, "training_", None) or {}
    same_store = bool(info) and info.get("store_id", "") == dataset.attrs.get("store_id", "") and \
        Path(info.get("store", "")).resolve() == Path(store).resolve()
    if same_store and info.get("split", "none") != "none":
        _, index = split_indices(dataset, info["split"], info.get("strategy"), info["test_fraction"], info["seed"])
        return index, f"held-out {info['split']} split of training"
    return dataset.indices(strategy), "all sequences" + (f" of strategy {strategy}" if strategy else "")


def evaluate_on_store(model, store: str | Path, *, touches: int = 1, rule: str = "log", strategy: str | None = None,
                      seed: int = 0) -> dict:
    """Accuracy of ``model`` on ``store`` (see :func:`evaluation_indices`), ``touches`` sequences of one object per
    decision fused by ``rule``.

    Returns:
        {"subset", "touches", "rule", "decisions", "accuracy", "accuracy_object_bootstrap", "per_class"} (JSON
        data) and, for figures, "truth", "predicted", "classes" (arrays) and "interval" (the Accuracy).

    Raises:
        InvalidArgumentError: touches < 1 or an unknown rule. ModelMismatchError: data from another sensor.
    """
    from fusion.decide import fuse_touches, touch_groups
    from fusion.evaluate import accuracy, per_class_accuracy
    from tactile.dataset import open_dataset

    dataset = open_dataset(store)
    index, subset = evaluation_indices(model, dataset, store, strategy)
    batch = dataset.load(index)
    if subset.startswith("held-out"):  # checked against what the model was fitted on (fusion.leakage)
        check_held_out(model, batch, f"{store}: {subset}", by_object="object" in subset)
    else:  # not a held-out part: say how much of it the model was fitted on, so the score is read for what it is
        trained_on = int(overlap(model, batch).sum())
        if trained_on:
            subset += f"; the model was fitted on {trained_on} of these {len(batch)} sequences: not a held-out score"
    classes = model.classes_.astype(str)
    truth = np.asarray(batch.class_names, dtype=object)[batch.labels].astype(str)
    foreign = sorted(set(truth.tolist()) - set(classes.tolist()))
    if foreign:
        raise DatasetError(f"{store}: classes {foreign[:5]} are not among the model's classes {classes.tolist()[:20]}"
                           " (a model can only be scored on classes it was trained on)")
    proba = model.predict_proba(batch)
    if touches > 1:
        try:
            groups = touch_groups(batch.object_ids, touches, seed=seed)
        except DatasetError as exc:
            raise DatasetError(f"{store}: touches={touches}: {exc}") from None
        proba = fuse_touches(proba[groups], rule=rule)
        truth = truth[groups[:, 0]]
        decision_groups = batch.object_ids[groups[:, 0]]
    else:
        decision_groups = batch.object_ids
    predicted = classes[np.argmax(proba, axis=1)]
    acc = accuracy(truth, predicted, seed=seed)
    by_object = accuracy(truth, predicted, groups=decision_groups, seed=seed)
    return {
        "subset": subset, "touches": touches, "rule": rule, "decisions": len(predicted), "accuracy": acc.to_dict(),
        "accuracy_object_bootstrap": by_object.to_dict(),
        "per_class": per_class_accuracy(truth, predicted, classes),
        "truth": truth, "predicted": predicted, "classes": classes, "interval": acc, "object_interval": by_object,
    }


__all__ = ["SPLITS", "TrainingRecord", "evaluate_on_store", "evaluation_indices", "split_indices", "train_on_store"]
