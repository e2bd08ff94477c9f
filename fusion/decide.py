"""Decisions from several touches: fuse the class probabilities of K sequences of the same object.

Three rules: ``"sum"`` (the paper's: add the probability vectors), ``"log"`` (add log probabilities, i.e.
treat the touches as independent evidence; a touch that rules a class out vetoes it) and ``"tempered"`` (the log rule
with the sum scaled by 1 / (1 + rho (K - 1)), rho = ``dependence`` in [0, 1]: touches of one object are not
independent; rho is fitted on held-out objects by :func:`fusion.openset.calibrate`, see :mod:`fusion.calibration`). Log probabilities are
floored at ``PROBA_FLOOR`` so a single zero does not give -inf.
"""

from __future__ import annotations

import numpy as np

from perception.errors import DatasetError, InvalidArgumentError

RULES = ("log", "sum", "tempered")
#: Probabilities below this count as this much in the log rule (keeps every sum finite).
PROBA_FLOOR = 1e-12


def fuse_touches(proba: np.ndarray, rule: str = "log", dependence: float = 0.0) -> np.ndarray:
    """Fuse (K, C) probabilities of K touches into one (C,) distribution; (N, K, C) gives (N, C).
    ``dependence``: rho of the ``"tempered"`` rule (0: the log rule).

    Raises:
        InvalidArgumentError: unknown rule, or a bad ``dependence``.
        DatasetError: bad shape, or non-finite / negative probabilities.
    """
    if rule not in RULES:
        raise InvalidArgumentError(f"unknown fusion rule {rule!r}; choose one of {', '.join(RULES)}")
    proba = np.asarray(proba, dtype=np.float64)
    if proba.ndim not in (2, 3) or proba.shape[-2] < 1 or proba.shape[-1] < 1:
        raise DatasetError(f"fuse_touches: expected (K, C) or (N, K, C) probabilities, got shape {proba.shape}")
    if not np.isfinite(proba).all() or (proba < 0).any():
        raise DatasetError("fuse_touches: probabilities must be finite and non-negative")
    if rule == "sum":
        score = proba.sum(axis=-2)
        total = score.sum(axis=-1, keepdims=True)
        return np.where(total > 0, score / np.where(total > 0, total, 1), 1.0 / proba.shape[-1])
    log_score = np.log(np.maximum(proba, PROBA_FLOOR)).sum(axis=-2)
    if rule == "tempered":
        from fusion.calibration import tempered_exponent

        log_score = log_score * tempered_exponent(proba.shape[-2], dependence)
    log_score -= log_score.max(axis=-1, keepdims=True)
    score = np.exp(log_score)
    return score / score.sum(axis=-1, keepdims=True)


def touch_groups(object_ids: np.ndarray, k: int, seed: int = 0, *, repeats: int = 1) -> np.ndarray:
    """(G, k) index arrays: groups of ``k`` distinct sequences of the same object, for multi-touch decisions.

    Each object's sequences are shuffled (seeded) and cut into groups of ``k`` (a remainder is dropped), and
    this is done ``repeats`` times with fresh shuffles, so every sequence is used about ``repeats`` times.

    Raises:
        DatasetError: k < 1, or no object has k sequences.
    """
    if int(k) != k or k < 1:
        raise InvalidArgumentError(f"touch_groups: k must be a positive integer, got {k!r}")
    object_ids = np.asarray(object_ids)
    rng = np.random.default_rng(seed)
    groups = []
    for _ in range(repeats):
        for obj in np.unique(object_ids):
            members = rng.permutation(np.flatnonzero(object_ids == obj))
            usable = len(members) - len(members) % k
            groups.extend(members[:usable].reshape(-1, k))
    if not groups:
        most = int(np.bincount(np.unique(object_ids, return_inverse=True)[1]).max()) if len(object_ids) else 0
        raise DatasetError(f"touch_groups: no object has {k} sequences to group into one decision of {k} touches "
                           f"(the most any object has: {most})")
    return np.asarray(groups, dtype=np.int64)


__all__ = ["PROBA_FLOOR", "RULES", "fuse_touches", "touch_groups"]
