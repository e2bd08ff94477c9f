"""Scores shared by the layers: the area under the ROC curve (attention's channel weights, the open-set reject)."""

from __future__ import annotations

import numpy as np

from perception.errors import DatasetError


def auroc(known, unknown) -> float:
    """Area under the ROC curve of telling ``known`` scores (positives, higher) from ``unknown`` ones: the
    probability that a random known score exceeds a random unknown one, ties counting one half (Mann-Whitney).

    Raises:
        DatasetError: an empty or non-finite set.
    """
    # Imported here: scipy.stats takes 0.6 s to import (every generation worker would pay it), only this needs it.
    from scipy.stats import rankdata

    known, unknown = np.asarray(known, dtype=np.float64).ravel(), np.asarray(unknown, dtype=np.float64).ravel()
    if len(known) == 0 or len(unknown) == 0 or not (np.isfinite(known).all() and np.isfinite(unknown).all()):
        raise DatasetError(f"auroc: need non-empty finite score sets, got {len(known)} known, {len(unknown)} unknown")
    ranks = rankdata(np.concatenate([known, unknown]))
    return float((ranks[: len(known)].sum() - len(known) * (len(known) + 1) / 2) / (len(known) * len(unknown)))


__all__ = ["auroc"]
