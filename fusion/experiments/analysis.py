"""Scoring cached predictions: accuracies with intervals, K-touch curves, the Pareto front of error vs time.

Intervals are the percentile bootstrap of :func:`fusion.evaluate.accuracy` (1000 resamples, seeded):
``by="decision"`` resamples test decisions (sequences or touch groups), ``by="object"`` resamples whole
objects (a cluster bootstrap: the honest interval when decisions about one object are correlated, as for
unseen objects and for several touch groups of one object).
"""

from __future__ import annotations

import numpy as np

from fusion.decide import fuse_touches, touch_groups
from fusion.evaluate import Accuracy, accuracy
from fusion.experiments.models import Predictions
from perception.errors import InvalidArgumentError

BOOTSTRAP = 1000
#: Times each object's sequences are shuffled and cut into K-touch groups (K > 1): which touches land together
#: is chance, and one cut moved K = 8 accuracies by up to 2 points (99 SHREC objects, 24 sequences each); the
#: estimate averages over the cuts (its interval still resamples objects).
TOUCH_REPEATS = 10


def _groups(pred: Predictions, k: int, seed: int, repeats: int | None) -> np.ndarray:
    """K-touch index groups of ``pred``: one cut for K = 1 (nothing to average), else ``repeats`` cuts."""
    repeats = TOUCH_REPEATS if repeats is None else repeats
    return touch_groups(pred.object_ids, k, seed=seed, repeats=1 if k == 1 else repeats)


def score(pred: Predictions, *, by: str = "decision", seed: int = 0) -> Accuracy:
    """Accuracy of single-sequence decisions with a 95 % interval (``by``: "decision" or "object")."""
    _check_by(by)
    return accuracy(pred.labels, pred.predicted, groups=pred.object_ids if by == "object" else None,
                    n_boot=BOOTSTRAP, seed=seed)


def touches_score(pred: Predictions, k: int, rule: str = "log", *, by: str = "object", seed: int = 0,
                  repeats: int | None = None) -> Accuracy:
    """Accuracy of decisions that fuse ``k`` sequences of the same object (disjoint groups per cut, seeded;
    ``repeats`` cuts, default :data:`TOUCH_REPEATS`).

    Raises:
        DatasetError: no object has ``k`` test sequences.
    """
    _check_by(by)
    groups = _groups(pred, k, seed, repeats)
    fused = fuse_touches(pred.proba[groups], rule=rule)
    predicted = np.asarray(pred.classes, dtype=object)[np.argmax(fused, axis=1)]
    first = groups[:, 0]
    return accuracy(pred.labels[first], predicted, groups=pred.object_ids[first] if by == "object" else None,
                    n_boot=BOOTSTRAP, seed=seed)


def object_accuracy(pred: Predictions, k: int = 1, rule: str = "log", *, seed: int = 0,
                    repeats: int | None = None) -> dict[str, float]:
    """{object name: share of its K-touch decisions that are right} (groups of ``k`` of its sequences, cut
    as in :func:`touches_score`).

    Raises:
        DatasetError: no object has ``k`` test sequences.
    """
    groups = _groups(pred, k, seed, repeats)
    fused = fuse_touches(pred.proba[groups], rule=rule)
    right = np.asarray(pred.classes, dtype=object)[np.argmax(fused, axis=1)] == pred.labels[groups[:, 0]]
    objects = np.asarray(pred.object_ids)[groups[:, 0]]
    return {pred.object_names[o]: float(right[objects == o].mean()) for o in np.unique(objects)}


def paired_difference(a: Predictions, b: Predictions, k: int = 1, rule: str = "log", *, seed: int = 0) -> dict:
    """Accuracy of ``a`` minus that of ``b`` on the objects both tested (paired object by object), K touches.

    Each object's accuracy is the share of its K-touch decisions that are right; the difference is the mean of
    the per-object differences, its 95 % interval the percentile bootstrap over objects (:data:`BOOTSTRAP`
    resamples), and ``detectable`` the smallest true difference this design finds with 80 % power at the 5 %
    level (two-sided normal approximation: (1.96 + 0.84) x the standard error of the mean difference).

    Returns:
        {"difference", "low", "high", "detectable", "n_objects"} (fractions, not percent).

    Raises:
        InvalidArgumentError: the two share fewer than two objects.
    """
    acc_a, acc_b = object_accuracy(a, k, rule, seed=seed), object_accuracy(b, k, rule, seed=seed)
    common = sorted(set(acc_a) & set(acc_b))
    if len(common) < 2:
        raise InvalidArgumentError(f"paired_difference: the predictions share {len(common)} objects; need 2 or more")
    diff = np.array([acc_a[o] - acc_b[o] for o in common])
    rng = np.random.default_rng(seed)
    boot = diff[rng.integers(0, len(diff), size=(BOOTSTRAP, len(diff)))].mean(axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    standard_error = diff.std(ddof=1) / np.sqrt(len(diff))
    return {"difference": float(diff.mean()), "low": float(low), "high": float(high),
            "detectable": float((1.96 + 0.84) * standard_error), "n_objects": len(common)}


def touch_curve(pred: Predictions, ks, rules=("log", "sum"), *, by: str = "object", seed: int = 0) -> list[dict]:
    """Rows {k, rule, accuracy} for every K in ``ks`` and fusion rule (K = 1 is the same for both rules)."""
    rows = []
    for rule in rules:
        for k in ks:
            rows.append({"k": int(k), "rule": rule, "accuracy": touches_score(pred, k, rule, by=by, seed=seed)})
    return rows


def _check_by(by: str) -> None:
    if by not in ("decision", "object"):
        raise InvalidArgumentError(f"bootstrap unit must be 'decision' or 'object', got {by!r}")


def pareto_front(times, errors) -> np.ndarray:
    """Indices of the points no other point beats in both time and error (lower is better), by time.

    A point is dominated when another is at least as fast and at least as accurate and strictly better in
    one; ties keep the first.
    """
    times, errors = np.asarray(times, dtype=np.float64), np.asarray(errors, dtype=np.float64)
    if times.shape != errors.shape or times.ndim != 1:
        raise InvalidArgumentError(f"pareto_front: need equal 1-D arrays, got {times.shape} and {errors.shape}")
    order = np.lexsort((errors, times))
    front, best = [], np.inf
    for i in order:
        if errors[i] < best:
            front.append(int(i))
            best = errors[i]
    return np.asarray(front, dtype=np.int64)


def name_operating_points(times, errors, front) -> dict[str, int]:
    """Named points of the front (indices into the points): ``fastest``, ``most accurate`` and ``knee``: the
    interior front point that removes the most error for its time, i.e. furthest from the straight line
    joining the two ends, with log10 time and error each scaled to [0, 1] between the ends."""
    front = np.asarray(front)
    if len(front) == 0:
        return {}
    t = np.log10(np.maximum(np.asarray(times, dtype=np.float64)[front], 1e-9))
    e = np.asarray(errors, dtype=np.float64)[front]
    names = {"fastest": int(front[0]), "most accurate": int(front[-1])}
    if len(front) > 2:
        span_t, span_e = t[-1] - t[0], e[-1] - e[0]
        norm_t = (t - t[0]) / span_t if span_t > 0 else np.zeros_like(t)
        norm_e = (e - e[0]) / span_e if span_e != 0 else np.zeros_like(e)
        # Most error removed for the time spent: furthest above the chord from (0, 0) to (1, 1).
        gain = norm_e - norm_t
        knee = int(np.argmax(gain[1:-1])) + 1
        names["knee"] = int(front[knee])
    return names


__all__ = ["BOOTSTRAP", "name_operating_points", "object_accuracy", "paired_difference", "pareto_front", "score",
           "touch_curve", "touches_score"]
