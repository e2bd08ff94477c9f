"""The paper's conventional classifier: contourlet + wavelet statistics, information gain, SOM, SVM or kNN.

One scikit-learn :class:`~sklearn.pipeline.Pipeline` (:func:`conventional_pipeline`)::

    SequenceSeries(cue)          batch -> 19 (normals) or 22 (invariant) series of P per sequence
    WaveletStatistics(F)         3-level db2 -> rms / std / skewness of each level and of the series
    InfoGainSelector(k)          mutual information with the class, seeded
    StandardScaler               (ours: PCA needs features on one scale; the SOM standardises too)
    SOMProjection(5) | PCA(5)    "SOM to 5": a 1 x 5 map groups the features; PC1 of each
    StandardScaler               the paper's z-score
    SVC(rbf, gamma 1, C 1) Platt-calibrated, seeded | KNeighborsClassifier(10, Euclidean)

:class:`ConventionalClassifier` wraps it with the :class:`~fusion.base.TactileClassifier` interface (input,
labels, sensor checks, save / load, multi-touch). :func:`cross_validate` is the paper's k-fold
cross-validation on the training part; it computes the contourlet features of the batch once.
"""

from __future__ import annotations

import logging

import numpy as np
from sklearn.base import clone
from sklearn.calibration import CalibratedClassifierCV
from sklearn.decomposition import PCA
from sklearn.model_selection import StratifiedKFold
from sklearn.neighbors import KNeighborsClassifier
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC

from fusion.base import TactileClassifier, as_batch
from fusion.cues import check_cue
from fusion.features import (
    InfoGainSelector,
    SequenceSeries,
    SOMProjection,
    WaveletStatistics,
    n_series,
    sequence_features,
)
from perception.errors import DatasetError
from tactile.explore import SequenceBatch

log = logging.getLogger(__name__)

KINDS = ("svm", "knn")
REDUCERS = ("som", "pca")


def _check_choice(name: str, value, choices) -> None:
    if value not in choices:
        raise DatasetError(f"unknown {name} {value!r}; choose one of {', '.join(choices)}")


def conventional_pipeline(
    kind: str = "svm",
    cue: str = "normals",
    n_select: int = 40,
    reduce: str = "som",
    n_components: int = 5,
    som_iterations: int = 5000,
    n_neighbors: int = 10,
    random_state: int = 0,
    calibration_folds: int = 5,
) -> Pipeline:
    """The paper's pipeline (module docstring), unfitted; ``fit`` / ``predict_proba`` take SequenceBatches.

    ``pipeline[1:]`` is the same pipeline on the (S, F * P) arrays of :func:`fusion.features.sequence_features`.
    The SVM's probabilities are Platt-scaled on ``calibration_folds`` stratified folds (as libsvm's
    ``probability=True``), then the SVM is refitted on all the training data.

    Raises:
        DatasetError: unknown kind, cue or reduce.
    """
    _check_choice("classifier kind", kind, KINDS)
    _check_choice("reduction", reduce, REDUCERS)
    check_cue(cue)
    if reduce == "som":
        reducer = SOMProjection(n_units=n_components, n_iterations=som_iterations, random_state=random_state)
    else:
        reducer = PCA(n_components=n_components, random_state=random_state)
    if kind == "svm":
        # Platt-scaled probabilities: scikit-learn 1.9 deprecates SVC(probability=True) for exactly this.
        classify = CalibratedClassifierCV(
            SVC(kernel="rbf", gamma=1.0, C=1.0, random_state=random_state),
            method="sigmoid", cv=calibration_folds, ensemble=False,
        )
    else:
        classify = KNeighborsClassifier(n_neighbors=n_neighbors, metric="euclidean")
    return Pipeline(
        [
            ("series", SequenceSeries(cue)),
            ("wavelet", WaveletStatistics(n_series=n_series(cue), wavelet="db2", level=3)),
            ("select", InfoGainSelector(k=n_select, random_state=random_state)),
            ("standardise", StandardScaler()),
            ("reduce", reducer),
            ("zscore", StandardScaler()),
            ("classify", classify),
        ]
    )


class ConventionalClassifier(TactileClassifier):
    """Contourlet / wavelet features with an SVM (``kind="svm"``) or kNN (``"knn"``), as in the paper.

    Parameters:
        kind: "svm" (RBF, gamma 1, C 1, Platt probabilities) or "knn" (k = ``n_neighbors``, Euclidean).
        cue: kinesthetic cue, "normals" (the paper's) or "invariant" (pose-invariant, :mod:`fusion.cues`).
        n_select: features kept by information gain (of 15 per series: 285 for normals, 330 invariant).
        reduce: "som" (the paper's SOM to ``n_components``) or "pca" (the baseline it is compared with).
        n_components: features after the reduction (5).
        som_iterations: SOM training steps.
        n_neighbors: kNN's k (10); lowered to the training-set size when that is smaller.
        random_state: seeds selection, SOM and PCA (the SVM and its unshuffled calibration folds are deterministic).

    Fitted: ``pipeline_`` (a :class:`~sklearn.pipeline.Pipeline` over SequenceBatches) and the base's attributes.
    """

    def __init__(
        self,
        kind: str = "svm",
        cue: str = "normals",
        n_select: int = 40,
        reduce: str = "som",
        n_components: int = 5,
        som_iterations: int = 5000,
        n_neighbors: int = 10,
        random_state: int = 0,
    ):
        self.kind = kind
        self.cue = cue
        self.n_select = n_select
        self.reduce = reduce
        self.n_components = n_components
        self.som_iterations = som_iterations
        self.n_neighbors = n_neighbors
        self.random_state = random_state

    def make_pipeline(self, y: np.ndarray | None = None) -> Pipeline:
        """The unfitted pipeline of these parameters; given the training labels ``y``, kNN's k is capped at
        their count and the SVM's calibration folds at the smallest class.

        Raises:
            DatasetError: unknown kind, cue or reduce; an SVM with a class of a single sequence (no calibration).
        """
        k, folds, components = self.n_neighbors, 5, self.n_components
        if y is not None:
            k = max(1, min(self.n_neighbors, len(y)))
            if self.reduce == "pca":  # PCA cannot give more components than samples or features
                components = max(1, min(self.n_components, self.n_select, len(y)))
            smallest = int(np.bincount(np.unique(y, return_inverse=True)[1]).min())
            if self.kind == "svm" and smallest < 2:
                raise DatasetError(
                    "the SVM calibrates its probabilities by cross-validation and needs at least 2 sequences "
                    "per class; a class has 1"
                )
            folds = min(5, smallest)
        return conventional_pipeline(
            kind=self.kind, cue=self.cue, n_select=self.n_select, reduce=self.reduce,
            n_components=components, som_iterations=self.som_iterations, n_neighbors=k,
            random_state=self.random_state, calibration_folds=folds,
        )

    def _fit(self, batch: SequenceBatch, y_index: np.ndarray) -> None:
        pipeline = self.make_pipeline(y_index)
        features = sequence_features(batch, self.cue)
        pipeline[1:].fit(features, y_index)  # the front step is stateless: fit the rest on its output
        self.pipeline_ = pipeline

    def _predict_proba(self, batch: SequenceBatch) -> np.ndarray:
        # Columns follow the labels seen in training, which are all of 0..C-1 (classes_ comes from them).
        return self.pipeline_.predict_proba(batch)


def cross_validate(clf: TactileClassifier, X, folds: int = 5, seed: int = 0) -> np.ndarray:
    """(folds,) test accuracies of ``clf`` in stratified, seeded k-fold cross-validation on ``X`` (a batch).

    For a :class:`ConventionalClassifier` the contourlet and cue series are computed once for the whole
    batch; any other classifier is cloned and fitted on each fold's sub-batch.

    Raises:
        DatasetError: unlabelled sequences, or a class with fewer sequences than ``folds``.
    """
    batch = as_batch(X)
    if (batch.labels < 0).any():
        raise DatasetError("cross_validate: some sequences have no label")
    counts = np.bincount(batch.labels)
    counts = counts[counts > 0]
    if folds < 2 or counts.min() < folds:
        raise DatasetError(
            f"cross_validate: {folds}-fold cross-validation needs folds >= 2 and at least {folds} sequences "
            f"per class; the smallest class has {counts.min()}"
        )
    splitter = StratifiedKFold(n_splits=folds, shuffle=True, random_state=seed)
    scores = []
    if isinstance(clf, ConventionalClassifier):
        features = sequence_features(batch, clf.cue)
        for train, test in splitter.split(features, batch.labels):
            tail = clf.make_pipeline(batch.labels[train])[1:]
            tail.fit(features[train], batch.labels[train])
            scores.append(float(np.mean(tail.predict(features[test]) == batch.labels[test])))
    else:
        for train, test in splitter.split(batch.labels, batch.labels):
            model = clone(clf).fit(batch.subset(train))
            scores.append(model.score(batch.subset(test)))
    log.info("%d-fold cross-validation of %s: %s", folds, type(clf).__name__, np.round(scores, 4))
    return np.array(scores)


__all__ = ["KINDS", "REDUCERS", "ConventionalClassifier", "conventional_pipeline", "cross_validate"]
