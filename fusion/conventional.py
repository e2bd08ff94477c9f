"""The paper's conventional classifier: contourlet + wavelet statistics, information gain, SOM, SVM or kNN.

One scikit-learn :class:`~sklearn.pipeline.Pipeline` (:func:`conventional_pipeline`)::

    SequenceSeries(cue)          batch -> 19 (normals) or 22 (invariant) series of P per sequence
    WaveletStatistics(F)         3-level db2 -> rms / std / skewness of each level and of the series
    InfoGainSelector(k)          mutual information with the class, seeded
    StandardScaler               (ours: PCA needs features on one scale; the SOM standardises too)
    SOMProjection(5) | PCA(5)    "SOM to 5": a 1 x 5 map groups the features; PC1 of each
    StandardScaler               the paper's z-score
    SVC(rbf, gamma 1, C 1) Platt-calibrated, seeded | KNeighborsClassifier(10, Euclidean)

The paper's five SOM features are a tight bottleneck on objects never trained on (unseen SHREC objects,
grouped 3-fold, blind, K = 8: SVM 82.5 %, kNN 82.8 %; without the reduction 89.9-91.2 % and 85.2-87.2 %).
``search="objects"`` (the default) therefore chooses among :data:`SEARCH_GRID` (the configured pipeline
first, then pipelines without the reduction) by grouped cross-validation over the *training* objects, and
refits the winner on all of them; ``search=None`` keeps the configured pipeline (the paper reproduction).

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
from sklearn.model_selection import StratifiedGroupKFold, StratifiedKFold
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
from perception.errors import DatasetError, InvalidArgumentError
from tactile.explore import SequenceBatch

log = logging.getLogger(__name__)

KINDS = ("svm", "knn")
REDUCERS = ("som", "pca", "none")
SEARCHES = (None, "objects")
#: Candidates of ``search="objects"`` per kind: parameter overrides of the configured pipeline (``{}``: as
#: configured). ``n_select=None`` keeps every feature; ``gamma="scale"`` is scikit-learn's 1 / (F var(X)).
SEARCH_GRID = {
    "svm": ({}, {"reduce": "none", "n_select": 40, "gamma": "scale", "C": 1.0},
            {"reduce": "none", "n_select": 40, "gamma": "scale", "C": 10.0},
            {"reduce": "none", "n_select": None, "gamma": "scale", "C": 1.0},
            {"reduce": "none", "n_select": None, "gamma": "scale", "C": 10.0}),
    "knn": ({}, {"reduce": "none", "n_select": 40}, {"reduce": "none", "n_select": None}),
}
#: Inner folds of the search (grouped by object, stratified by class).
SEARCH_FOLDS = 3


def _check_choice(name: str, value, choices) -> None:
    if value not in choices:
        raise InvalidArgumentError(f"unknown {name} {value!r}; choose one of {', '.join(choices)}")


def conventional_pipeline(
    kind: str = "svm",
    cue: str = "invariant",
    n_select: int | None = 40,
    reduce: str = "som",
    n_components: int = 5,
    som_iterations: int = 5000,
    n_neighbors: int = 10,
    random_state: int = 0,
    calibration_folds: int = 5,
    C: float = 1.0,
    gamma: float | str = 1.0,
) -> Pipeline:
    """The paper's pipeline (module docstring), unfitted; ``fit`` / ``predict_proba`` take SequenceBatches.
    ``n_select=None`` drops the selection step, ``reduce="none"`` the reduction and its z-score.

    ``pipeline[1:]`` is the same pipeline on the (S, F * P) arrays of :func:`fusion.features.sequence_features`.
    The SVM's probabilities are Platt-scaled on ``calibration_folds`` stratified folds (as libsvm's
    ``probability=True``), then the SVM is refitted on all the training data.

    Raises:
        DatasetError: unknown kind, cue or reduce.
    """
    _check_choice("classifier kind", kind, KINDS)
    _check_choice("reduction", reduce, REDUCERS)
    check_cue(cue)
    if kind == "svm":
        # Platt-scaled probabilities: scikit-learn 1.9 deprecates SVC(probability=True) for exactly this.
        classify = CalibratedClassifierCV(
            SVC(kernel="rbf", gamma=gamma, C=C, random_state=random_state),
            method="sigmoid", cv=calibration_folds, ensemble=False,
        )
    else:
        classify = KNeighborsClassifier(n_neighbors=n_neighbors, metric="euclidean")
    steps = [("series", SequenceSeries(cue)),
             ("wavelet", WaveletStatistics(n_series=n_series(cue), wavelet="db2", level=3))]
    if n_select is not None:
        steps.append(("select", InfoGainSelector(k=n_select, random_state=random_state)))
    steps.append(("standardise", StandardScaler()))
    if reduce == "som":
        steps.append(("reduce", SOMProjection(n_units=n_components, n_iterations=som_iterations,
                                              random_state=random_state)))
    elif reduce == "pca":
        steps.append(("reduce", PCA(n_components=n_components, random_state=random_state)))
    if reduce != "none":
        steps.append(("zscore", StandardScaler()))
    return Pipeline([*steps, ("classify", classify)])


class ConventionalClassifier(TactileClassifier):
    """Contourlet / wavelet features with an SVM (``kind="svm"``) or kNN (``"knn"``), as in the paper.

    Parameters:
        kind: "svm" (RBF, gamma 1, C 1, Platt probabilities) or "knn" (k = ``n_neighbors``, Euclidean).
        cue: kinesthetic cue, "invariant" (pose-free, the default, :mod:`fusion.cues`) or "normals" (the paper's, pose-dependent).
        n_select: features kept by information gain (of 15 per series: 285 for normals, 330 invariant; None:
            all, no selection step).
        reduce: "som" (the paper's SOM to ``n_components``), "pca" (the baseline it is compared with) or
            "none" (the selected features themselves).
        n_components: features after the reduction (5).
        som_iterations: SOM training steps.
        n_neighbors: kNN's k (10); lowered to the training-set size when that is smaller.
        C, gamma: the SVM's regularisation and RBF width (the paper: 1 and 1; ``"scale"`` as in scikit-learn).
        random_state: seeds selection, SOM, PCA and the search's folds (the SVM and its unshuffled calibration
            folds are deterministic).
        search: ``"objects"``: choose the pipeline among :data:`SEARCH_GRID` by grouped cross-validation over
            the training objects (:data:`SEARCH_FOLDS` folds, accuracy per sequence; ties keep the earlier
            candidate), then refit it on all of them; needs every class to have two or more objects, else the
            configured pipeline is used. None: the configured pipeline.

    Fitted: ``pipeline_`` (a :class:`~sklearn.pipeline.Pipeline` over SequenceBatches), ``search_`` (the chosen
    candidate's index in ``SEARCH_GRID[kind]`` and each candidate's mean inner accuracy; None without a
    search) and the base's attributes.

    Examples:
        >>> from fusion.experiments.touch import touch_objects
        >>> from perception.shapes import make_object
        >>> objects = [make_object("box", 0), make_object("can", 0)]
        >>> batch = touch_objects(objects, ["box", "can"], "blind", 4, probes=10)  # 8 labelled sequences, 32 x 32
        >>> model = ConventionalClassifier(kind="svm").fit(batch)
        >>> list(model.classes_), model.predict(batch).shape
        (['box', 'can'], (8,))
    """

    def __init__(
        self,
        kind: str = "svm",
        cue: str = "invariant",
        n_select: int = 40,
        reduce: str = "som",
        n_components: int = 5,
        som_iterations: int = 5000,
        n_neighbors: int = 10,
        C: float = 1.0,
        gamma: float | str = 1.0,
        random_state: int = 0,
        search: str | None = "objects",
    ):
        self.kind = kind
        self.cue = cue
        self.n_select = n_select
        self.reduce = reduce
        self.n_components = n_components
        self.som_iterations = som_iterations
        self.n_neighbors = n_neighbors
        self.C = C
        self.gamma = gamma
        self.random_state = random_state
        self.search = search

    def _params(self, candidate: int | None = None) -> dict:
        """The pipeline parameters: the configured ones, overridden by ``SEARCH_GRID[kind][candidate]`` (the
        fitted search's choice when ``candidate`` is None)."""
        params = {"n_select": self.n_select, "reduce": self.reduce, "C": self.C, "gamma": self.gamma}
        if candidate is None:
            candidate = (getattr(self, "search_", None) or {}).get("chosen")
        if candidate is not None:
            params |= SEARCH_GRID[self.kind][candidate]
        return params

    def make_pipeline(self, y: np.ndarray | None = None, candidate: int | None = None) -> Pipeline:
        """The unfitted pipeline of these parameters (or of a search candidate, see :meth:`_params`); given the
        training labels ``y``, kNN's k is capped at their count and the SVM's calibration folds at the
        smallest class.

        Raises:
            DatasetError: unknown kind, cue or reduce; an SVM with a class of a single sequence (no calibration).
        """
        _check_choice("classifier kind", self.kind, KINDS)
        _check_choice("search", self.search, SEARCHES)
        params = self._params(candidate)
        if params["n_select"] is not None and (int(params["n_select"]) != params["n_select"] or params["n_select"] < 1):
            raise InvalidArgumentError(f"n_select must be a positive integer or None, got {params['n_select']!r}")
        k, folds, components = self.n_neighbors, 5, self.n_components
        if y is not None:
            k = max(1, min(self.n_neighbors, len(y)))
            if params["reduce"] == "pca":  # PCA cannot give more components than samples or features
                components = max(1, min(self.n_components, params["n_select"] or components, len(y)))
            smallest = int(np.bincount(np.unique(y, return_inverse=True)[1]).min())
            if self.kind == "svm" and smallest < 2:
                raise DatasetError(
                    "the SVM calibrates its probabilities by cross-validation and needs at least 2 sequences "
                    "per class; a class has 1"
                )
            folds = min(5, smallest)
        return conventional_pipeline(
            kind=self.kind, cue=self.cue, n_components=components, som_iterations=self.som_iterations,
            n_neighbors=k, random_state=self.random_state, calibration_folds=folds, **params,
        )

    def _fit(self, batch: SequenceBatch, y_index: np.ndarray) -> None:
        features = sequence_features(batch, self.cue)
        self.search_ = None
        # The front step (series) is stateless and the wavelet step, the same in every candidate, stateless but
        # for its input check: the statistics of every sequence are computed once, for the search and the fit.
        wavelet = self.make_pipeline(y_index)[1]
        statistics = wavelet.fit_transform(features, y_index)
        if self.search == "objects":
            self.search_ = self._search(statistics, y_index, batch.object_ids)
        pipeline = self.make_pipeline(y_index).set_params(wavelet=wavelet)
        pipeline[2:].fit(statistics, y_index)
        self.pipeline_ = pipeline

    def _search(self, statistics: np.ndarray, y: np.ndarray, objects: np.ndarray) -> dict | None:
        """Mean inner accuracy of every candidate over folds of whole training objects, and the best one;
        None (configured pipeline) when a class has fewer than two objects or a fold would lack a class.
        ``statistics``: the wavelet step's output for every training sequence (each candidate's ``[2:]`` input)."""
        objects = np.asarray(objects)
        n_folds = min(SEARCH_FOLDS, *(len(np.unique(objects[y == c])) for c in np.unique(y)))
        folds = [] if n_folds < 2 else list(StratifiedGroupKFold(n_splits=n_folds, shuffle=True,
                                                                 random_state=self.random_state).split(statistics, y, objects))
        # every inner training fold must hold every class (the SVM's Platt folds: two sequences of each)
        needed = 2 if self.kind == "svm" else 1
        if not folds or any(np.bincount(y[train], minlength=len(self.classes_)).min() < needed for train, _ in folds):
            log.info("pipeline search skipped: too few training objects per class for grouped folds")
            return None
        scores = []
        for candidate in range(len(SEARCH_GRID[self.kind])):
            correct = []
            for train, test in folds:
                tail = self.make_pipeline(y[train], candidate)[2:]
                tail.fit(statistics[train], y[train])
                correct.append(float(np.mean(tail.predict(statistics[test]) == y[test])))
            scores.append(round(float(np.mean(correct)), 6))
        chosen = int(np.argmax(scores))  # the first best: the configured pipeline wins ties
        log.info("pipeline search (%s): inner accuracies %s, chose %s", self.kind, scores, SEARCH_GRID[self.kind][chosen])
        return {"chosen": chosen, "scores": scores}

    def _predict_proba(self, batch: SequenceBatch) -> np.ndarray:
        # Columns follow the labels seen in training, which are all of 0..C-1 (classes_ comes from them).
        return self.pipeline_.predict_proba(batch)

    # ------------------------------------------------------------------------------- persistence
    #: Parameters that fitting sets from the training data (see make_pipeline), stored with the model.
    _DATA_PARAMS = ("reduce__n_components", "classify__n_neighbors", "classify__cv")

    def _model_state(self, arrays: dict[str, np.ndarray]) -> dict:
        """The pipeline as data: its data-dependent parameters, each fitted step's arrays, and the classifier
        (kNN: its training points; SVM: support vectors, dual coefficients, intercepts and Platt sigmoids)."""
        from fusion.modelfile import encode

        pipeline = self.pipeline_
        params = pipeline.get_params()
        steps = {name: encode(_fitted(step), f"pipeline.{name}", arrays) for name, step in pipeline.steps[1:-1]}
        head = pipeline[-1]
        if self.kind == "knn":
            classify = {"fit_X": encode(head._fit_X, "knn.fit_X", arrays), "y": encode(head._y, "knn.y", arrays),
                        "classes": encode(head.classes_, "knn.classes", arrays)}
        else:
            classify = {
                "classes": encode(head.classes_, "svm.classes", arrays), "n_features_in": int(head.n_features_in_),
                "calibrated": [
                    {"svc": encode(_fitted(c.estimator), f"svm.{i}.svc", arrays),
                     "classes": encode(c.classes, f"svm.{i}.classes", arrays),
                     "sigmoids": [[float(s.a_), float(s.b_)] for s in c.calibrators]}
                    for i, c in enumerate(head.calibrated_classifiers_)
                ],
            }
        return {
            "fitted": encode(self._fitted_attributes(exclude=("pipeline_",)), "fitted", arrays),
            "data_params": {k: int(params[k]) for k in self._DATA_PARAMS if k in params},
            "steps": steps, "classify": classify,
        }

    def _restore_state(self, state: dict, arrays: dict[str, np.ndarray], where: str) -> None:
        """Rebuild the pipeline from this classifier's parameters (never from the file), set the stored arrays
        on its steps, check the SVM's arrays are consistent (libsvm reads them unchecked), refit the kNN index
        on the stored points, and run one prediction to prove the steps fit together."""
        from fusion.base import set_fitted
        from fusion.modelfile import decode
        from perception.errors import ModelFileError

        set_fitted(self, state.get("fitted"), arrays, where, exclude=("pipeline_",))
        search = getattr(self, "search_", None)
        if search is not None and self.kind in KINDS and not (isinstance(search, dict) and isinstance(search.get("chosen"), int)
                                       and not isinstance(search["chosen"], bool)
                                       and 0 <= search["chosen"] < len(SEARCH_GRID.get(self.kind, ()))):
            raise ModelFileError(f"{where}: the model's pipeline search result is not a candidate of {self.kind!r}")
        pipeline = self.make_pipeline()
        data_params = state.get("data_params")
        defaults = pipeline.get_params()
        if not isinstance(data_params, dict) or not set(data_params) <= set(self._DATA_PARAMS):
            raise ModelFileError(f"{where}: bad pipeline parameters in the model")
        for key, value in data_params.items():
            if key not in defaults or not isinstance(value, int) or isinstance(value, bool) or not (
                    1 <= value <= defaults[key]):
                raise ModelFileError(f"{where}: pipeline parameter {key} = {str(value)[:20]} outside 1..{defaults.get(key)}")
        pipeline.set_params(**data_params)
        steps = state.get("steps")
        names = [name for name, _ in pipeline.steps[1:-1]]
        if not isinstance(steps, dict) or sorted(steps) != sorted(names):
            raise ModelFileError(f"{where}: the model's pipeline steps are not {names}")
        for name in names:
            set_fitted(pipeline.named_steps[name], steps[name], arrays, where)
        classify = state.get("classify")
        if not isinstance(classify, dict):
            raise ModelFileError(f"{where}: the model lacks its classifier's state")
        n_classes = len(self.classes_)
        if self.kind == "knn":
            points = {k: decode(classify.get(k), arrays, where) for k in ("fit_X", "y", "classes")}
            _restore_knn(pipeline[-1], points, n_classes, where)
        else:
            _restore_svm(pipeline[-1], classify, n_classes, arrays, where)
        for name, value in _arrays_of(pipeline):
            if value.dtype.kind == "f" and not np.isfinite(value).all():
                raise ModelFileError(f"{where}: {name} of the model holds NaN or Inf")
        width = n_series(self.cue) * int(self.n_probes_)
        try:
            with np.errstate(all="ignore"):  # a hostile file's numbers (a zero scale) must not warn before the refusal
                proba = pipeline[1:].predict_proba(np.zeros((1, width)))
        except (ValueError, TypeError, IndexError, AttributeError) as exc:
            raise ModelFileError(f"{where}: the model's pipeline steps do not fit together ({str(exc)[:200]})") from None
        if proba.shape != (1, n_classes):
            raise ModelFileError(f"{where}: the model gives {proba.shape[1]} probabilities for {n_classes} classes")
        self.pipeline_ = pipeline


def _fitted(estimator) -> dict:
    """A scikit-learn estimator's fitted attributes (``name_`` or ``_name``, not parameters; the constructor sets
    the rest)."""
    from fusion.base import is_fitted_name

    params = set(estimator.get_params(deep=False))
    return {k: v for k, v in vars(estimator).items() if k not in params and is_fitted_name(k)}


def _arrays_of(pipeline: Pipeline):
    """(name, array) of every numeric array attribute of the pipeline's steps (and the SVMs inside)."""
    objects = [(name, step) for name, step in pipeline.steps]
    head = pipeline[-1]
    for i, c in enumerate(getattr(head, "calibrated_classifiers_", [])):
        objects.append((f"svm {i}", c.estimator))
    for name, obj in objects:
        for key, value in vars(obj).items():
            if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
                yield f"{name}.{key}", value


def _restore_knn(knn: KNeighborsClassifier, state: dict, n_classes: int, where: str) -> None:
    """Refit the kNN on its stored training points: the same points give the same neighbour index."""
    from perception.errors import ModelFileError

    fit_x, y, classes = state.get("fit_X"), state.get("y"), state.get("classes")
    if not (isinstance(fit_x, np.ndarray) and fit_x.dtype == np.float64 and fit_x.ndim == 2 and len(fit_x) >= 1
            and isinstance(y, np.ndarray) and y.dtype.kind == "i" and y.shape == (len(fit_x),)
            and isinstance(classes, np.ndarray) and np.array_equal(classes, np.arange(n_classes))
            and y.min() >= 0 and y.max() < n_classes and len(np.unique(y)) == n_classes):
        raise ModelFileError(f"{where}: the kNN's training points, labels or classes are inconsistent")
    if knn.n_neighbors > len(fit_x):
        raise ModelFileError(f"{where}: the kNN has k = {knn.n_neighbors} but {len(fit_x)} training points")
    knn.fit(fit_x, classes[y])


def _restore_svm(head: CalibratedClassifierCV, state: dict, n_classes: int, arrays, where: str) -> None:
    """Rebuild the Platt-calibrated SVM from its stored arrays, checked for the consistency libsvm assumes."""
    from sklearn.calibration import _CalibratedClassifier, _SigmoidCalibration

    from fusion.base import set_fitted
    from fusion.modelfile import decode
    from perception.errors import ModelFileError

    classes, calibrated = decode(state.get("classes"), arrays, where), state.get("calibrated")
    n_features = state.get("n_features_in")
    if not (isinstance(classes, np.ndarray) and np.array_equal(classes, np.arange(n_classes))
            and isinstance(calibrated, list) and 1 <= len(calibrated) <= 100
            and all(isinstance(entry, dict) for entry in calibrated)
            and isinstance(n_features, int) and not isinstance(n_features, bool) and n_features >= 1):
        raise ModelFileError(f"{where}: the SVM's classes or calibration are inconsistent")
    models = []
    for entry in calibrated:
        svc = clone(head.estimator)
        set_fitted(svc, entry.get("svc"), arrays, where)
        _check_svc(svc, n_classes, n_features, where)
        sigmoids = entry.get("sigmoids")
        n_sigmoids = 1 if n_classes == 2 else n_classes
        if not (isinstance(sigmoids, list) and len(sigmoids) == n_sigmoids and all(
                isinstance(p, list) and len(p) == 2 and all(isinstance(v, float) and np.isfinite(v) for v in p)
                for p in sigmoids)):
            raise ModelFileError(f"{where}: the SVM's Platt sigmoids are inconsistent")
        calibrators = []
        for a, b in sigmoids:
            sigmoid = _SigmoidCalibration()
            sigmoid.a_, sigmoid.b_ = np.float64(a), np.float64(b)
            calibrators.append(sigmoid)
        if not np.array_equal(decode(entry.get("classes"), arrays, where), np.arange(n_classes)):
            raise ModelFileError(f"{where}: the SVM's calibrated classes are inconsistent")
        models.append(_CalibratedClassifier(svc, calibrators, classes=np.arange(n_classes), method=head.method))
    head.classes_, head.n_features_in_, head.calibrated_classifiers_ = classes, n_features, models


def _check_svc(svc: SVC, n_classes: int, n_features: int, where: str) -> None:
    """The shapes and dtypes libsvm's prediction reads without checking (a mismatch would read out of bounds)."""
    from perception.errors import ModelFileError

    def array(name, dtype, shape):
        value = getattr(svc, name, None)
        if not (isinstance(value, np.ndarray) and value.dtype == dtype and value.shape == shape
                and value.flags.c_contiguous):
            raise ModelFileError(f"{where}: the SVM's {name} must be {np.dtype(dtype)} of shape {shape}")
        return value

    pairs = n_classes * (n_classes - 1) // 2
    counts = array("_n_support", np.int32, (n_classes,))
    n_sv = int(counts.sum()) if (counts >= 0).all() else -1
    vectors = getattr(svc, "support_vectors_", None)
    if n_sv < 1 or not isinstance(vectors, np.ndarray) or len(vectors) != n_sv:
        raise ModelFileError(f"{where}: the SVM's support vector counts do not match its support vectors")
    array("support_vectors_", np.float64, (n_sv, n_features))
    array("support_", np.int32, (n_sv,))
    for name in ("_dual_coef_", "dual_coef_"):
        array(name, np.float64, (n_classes - 1, n_sv))
    for name in ("_intercept_", "intercept_"):
        array(name, np.float64, (pairs,))
    for name in ("_probA", "_probB"):
        value = getattr(svc, name, None)
        if not (isinstance(value, np.ndarray) and value.dtype == np.float64 and value.shape in ((0,), (pairs,))):
            raise ModelFileError(f"{where}: the SVM's {name} is inconsistent")
    array("class_weight_", np.float64, (n_classes,))
    array("classes_", np.int64, (n_classes,))
    gamma, shape = getattr(svc, "_gamma", None), getattr(svc, "shape_fit_", None)
    if not (isinstance(gamma, float) and np.isfinite(gamma) and gamma > 0 and getattr(svc, "_sparse", None) is False
            and getattr(svc, "n_features_in_", None) == n_features and isinstance(shape, tuple) and len(shape) == 2
            and shape[1] == n_features and getattr(svc, "fit_status_", None) == 0):
        raise ModelFileError(f"{where}: the SVM's kernel settings or fitted shape are inconsistent")


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


__all__ = ["KINDS", "REDUCERS", "SEARCHES", "SEARCH_FOLDS", "SEARCH_GRID", "ConventionalClassifier", "conventional_pipeline", "cross_validate"]
