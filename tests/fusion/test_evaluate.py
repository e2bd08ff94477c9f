"""Evaluation helpers against hand counts and scikit-learn's metrics."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.metrics import confusion_matrix as sk_confusion

from fusion.evaluate import (
    accuracy,
    confusion,
    markdown_table,
    per_class_accuracy,
    plot_confusion,
    table1_rows,
)
from perception.errors import DatasetError


def test_accuracy_value_and_interval():
    y_true = np.array(["a"] * 80 + ["b"] * 20)
    y_pred = y_true.copy()
    y_pred[:10] = "b"  # 90 of 100 right
    acc = accuracy(y_true, y_pred, seed=0)
    assert acc.value == pytest.approx(0.9) and acc.n == 100
    # Binomial standard error sqrt(.9 * .1 / 100) = 0.03: the 95 % interval is about +-0.06.
    assert acc.low < 0.9 < acc.high
    assert 0.04 < acc.high - acc.value < 0.08 and 0.04 < acc.value - acc.low < 0.08
    assert accuracy(y_true, y_pred, seed=0) == acc  # seeded


def test_perfect_accuracy_has_a_degenerate_interval():
    acc = accuracy([1, 2, 3], [1, 2, 3])
    assert (acc.value, acc.low, acc.high) == (1.0, 1.0, 1.0)


def test_grouped_bootstrap_is_wider_when_errors_cluster_in_groups():
    y_true = np.zeros(200, dtype=int)
    y_pred = np.zeros(200, dtype=int)
    y_pred[:40] = 1  # all the errors on the first 4 of 20 objects
    groups = np.repeat(np.arange(20), 10)
    flat, grouped = accuracy(y_true, y_pred), accuracy(y_true, y_pred, groups=groups)
    assert flat.value == grouped.value == pytest.approx(0.8)
    assert grouped.high - grouped.low > 1.5 * (flat.high - flat.low)


def test_confusion_matches_scikit_learn():
    rng = np.random.default_rng(0)
    classes = ["cup", "box", "can"]
    y_true, y_pred = rng.choice(classes, 300), rng.choice(classes, 300)
    np.testing.assert_array_equal(confusion(y_true, y_pred, classes), sk_confusion(y_true, y_pred, labels=classes))
    recall = per_class_accuracy(y_true, y_pred, classes)
    for c in classes:
        assert recall[c] == pytest.approx(np.mean(y_pred[y_true == c] == c))


def test_labels_outside_the_classes_are_refused():
    with pytest.raises(DatasetError, match="not among the classes"):
        confusion(["a", "z"], ["a", "a"], ["a", "b"])
    with pytest.raises(DatasetError):
        accuracy([], [])


def test_confusion_figure_is_written(tmp_path):
    path = plot_confusion(np.array([[5, 1], [0, 4]]), ["a", "b"], tmp_path / "c.png", title="t")
    assert path.stat().st_size > 1000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_table1_rows_put_ours_next_to_the_paper():
    rows = table1_rows({"cnn": {"guided": accuracy([1, 1], [1, 1])}})
    assert rows[0]["paper guided"] == "98.97 %" and rows[0]["paper blind"] == "83.29 %"
    assert rows[0]["guided"].startswith("100.0 %") and rows[0]["blind"] == "-"
    assert markdown_table(rows).splitlines()[0] == "| classifier | guided | paper guided | blind | paper blind |"
