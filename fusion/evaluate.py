"""Measuring recognition: accuracy with a 95 % interval, per-class accuracy, confusion matrices, Table-1 rows.

Intervals are percentile bootstraps: resample the test decisions (sequences, or touch groups) with
replacement ``n_boot`` times, seeded; with ``groups`` (e.g. object ids) whole groups are resampled, which is
the honest interval when decisions about the same object are correlated.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from perception.atomic import save_figure
from perception.errors import DatasetError

#: Test accuracy (%) in Table 1 of Rouhafzay & Cretu (2019): classifier -> (guided, blind).
PAPER_TABLE1 = {"cnn": (98.97, 83.29), "svm": (88.44, 77.21), "knn": (86.07, 73.11)}


@dataclass(frozen=True)
class Accuracy:
    """An accuracy (fraction in [0, 1]) with its bootstrap 95 % interval and the number of decisions."""

    value: float
    low: float
    high: float
    n: int

    def percent(self) -> str:
        """'98.3 % [97.9, 98.7]'."""
        return f"{100 * self.value:.1f} % [{100 * self.low:.1f}, {100 * self.high:.1f}]"

    def to_dict(self) -> dict:
        return asdict(self)


def _check_pair(y_true, y_pred) -> tuple[np.ndarray, np.ndarray]:
    y_true, y_pred = np.asarray(y_true), np.asarray(y_pred)
    if y_true.shape != y_pred.shape or y_true.ndim != 1 or len(y_true) == 0:
        raise DatasetError(f"need two equal non-empty 1-D label arrays, got {y_true.shape} and {y_pred.shape}")
    return y_true, y_pred


def accuracy(y_true, y_pred, *, groups=None, n_boot: int = 1000, seed: int = 0) -> Accuracy:
    """Accuracy of ``y_pred`` against ``y_true`` with a percentile-bootstrap 95 % interval.

    Args:
        groups: optional (N,) group of each decision (e.g. object id): whole groups are resampled.

    Raises:
        DatasetError: empty or mismatched arrays.
    """
    y_true, y_pred = _check_pair(y_true, y_pred)
    correct = (y_true.astype(str) == y_pred.astype(str)).astype(np.float64)
    rng = np.random.default_rng(seed)
    if groups is None:
        draws = rng.integers(0, len(correct), size=(n_boot, len(correct)))
        boot = correct[draws].mean(axis=1)
    else:
        groups = np.asarray(groups)
        if groups.shape != correct.shape:
            raise DatasetError(f"groups shape {groups.shape} does not match {correct.shape} decisions")
        _, inverse = np.unique(groups, return_inverse=True)
        hits = np.bincount(inverse, weights=correct)
        sizes = np.bincount(inverse).astype(np.float64)
        draws = rng.integers(0, len(sizes), size=(n_boot, len(sizes)))
        boot = hits[draws].sum(axis=1) / sizes[draws].sum(axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    return Accuracy(float(correct.mean()), float(low), float(high), len(correct))


def confusion(y_true, y_pred, classes) -> np.ndarray:
    """(C, C) counts: row = true class, column = predicted class, in ``classes`` order.

    Raises:
        DatasetError: a label not in ``classes``.
    """
    y_true, y_pred = _check_pair(y_true, y_pred)
    classes = [str(c) for c in classes]
    index = {c: i for i, c in enumerate(classes)}
    unknown = (set(y_true.astype(str)) | set(y_pred.astype(str))) - set(index)
    if unknown:
        raise DatasetError(f"labels {sorted(str(u) for u in unknown)[:5]} are not among the classes {classes}")
    rows = np.array([index[c] for c in y_true.astype(str)])
    cols = np.array([index[c] for c in y_pred.astype(str)])
    matrix = np.zeros((len(classes), len(classes)), dtype=np.int64)
    np.add.at(matrix, (rows, cols), 1)
    return matrix


def per_class_accuracy(y_true, y_pred, classes) -> dict[str, float]:
    """Recall of each class (0 where a class has no test decision is reported as NaN-free ``None``)."""
    matrix = confusion(y_true, y_pred, classes)
    totals = matrix.sum(axis=1)
    return {
        str(c): (float(matrix[i, i] / totals[i]) if totals[i] else None) for i, c in enumerate(classes)
    }


def plot_confusion(matrix: np.ndarray, classes, path: str | Path, title: str = "") -> Path:
    """Row-normalised confusion matrix with class names and counts, written atomically to ``path`` (PNG)."""
    from matplotlib.figure import Figure

    matrix = np.asarray(matrix)
    totals = matrix.sum(axis=1, keepdims=True)
    share = matrix / np.where(totals > 0, totals, 1)
    n = len(classes)
    fig = Figure(figsize=(1.2 + 0.55 * n, 1.0 + 0.5 * n), layout="constrained")
    ax = fig.add_subplot()
    image = ax.imshow(share, vmin=0, vmax=1, cmap="Blues")
    ax.set_xticks(range(n), [str(c) for c in classes], rotation=45, ha="right")
    ax.set_yticks(range(n), [str(c) for c in classes])
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    for i in range(n):
        for j in range(n):
            if matrix[i, j]:
                ax.text(j, i, str(matrix[i, j]), ha="center", va="center", fontsize=7,
                        color="white" if share[i, j] > 0.5 else "black")
    fig.colorbar(image, ax=ax, shrink=0.8, label="share of the true class")
    if title:
        ax.set_title(title, fontsize=9)
    return save_figure(fig, path, dpi=120)


def table1_rows(results: dict[str, dict[str, Accuracy]]) -> list[dict]:
    """Rows of a Table-1 comparison: ``results[classifier][strategy]`` next to the paper's numbers."""
    rows = []
    for clf, by_strategy in results.items():
        paper = PAPER_TABLE1.get(clf.split(" ")[0].split("-")[0].lower())
        row = {"classifier": clf}
        for i, strategy in enumerate(("guided", "blind")):
            acc = by_strategy.get(strategy)
            row[strategy] = acc.percent() if acc else "-"
            row[f"paper {strategy}"] = f"{paper[i]:.2f} %" if paper else "-"
        rows.append(row)
    return rows


def markdown_table(rows: list[dict]) -> str:
    """A Markdown table of dict rows (columns from the first row)."""
    if not rows:
        return ""
    columns = list(rows[0])
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(row.get(c, "")) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


__all__ = [
    "PAPER_TABLE1",
    "Accuracy",
    "accuracy",
    "confusion",
    "markdown_table",
    "per_class_accuracy",
    "plot_confusion",
    "table1_rows",
]
