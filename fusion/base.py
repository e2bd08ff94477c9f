"""What every visuotactile classifier shares: input handling, sensor compatibility, multi-touch, save / load.

A classifier takes tactile sequences as a :class:`~tactile.explore.SequenceBatch`, an opened dataset
(:func:`tactile.dataset.open_dataset`) or the path of a dataset store, with the scikit-learn interface:
``fit(X, y=None)`` (``y`` defaults to the batch's labels), ``predict_proba``, ``predict``, ``score`` and
``classes_`` (class *names*). It remembers the sensor specification, probe count and taxel grid it was
trained on and refuses data from another sensor (:class:`ModelMismatchError`); taxel noise and dead
taxels are read-out conditions, not geometry, so they may differ (that is the noise experiment).

Models are saved with :meth:`TactileClassifier.save` as a pickle holding the estimator and a metadata
header (classes, sensor spec, probes, cue, library versions). Pickles run code when loaded: load only
models you trust.
"""

from __future__ import annotations

import logging
import pickle
import platform
from pathlib import Path

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin

from perception.atomic import atomic_path
from perception.errors import DatasetError, ModelMismatchError
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Sensor settings that may differ between training and use (read-out conditions, not geometry).
READOUT_SETTINGS = ("noise_std", "dead_taxel_rate")
MODEL_FORMAT = 1


def as_batch(X) -> SequenceBatch:
    """``X`` as a :class:`SequenceBatch`: a batch as is, an opened dataset or a store path loaded whole.

    Raises:
        DatasetError: anything else, or an empty batch.
    """
    if isinstance(X, SequenceBatch):
        batch = X
    elif isinstance(X, (str, Path)):
        from tactile.dataset import open_dataset

        batch = open_dataset(X).load()
    elif hasattr(X, "load") and hasattr(X, "sensor_spec"):
        batch = X.load()
    else:
        raise DatasetError(
            f"expected a SequenceBatch, an opened dataset or a store path, got {type(X).__name__}"
        )
    if len(batch) == 0:
        raise DatasetError("no sequences given")
    if not np.isfinite(batch.frames).all():
        raise DatasetError("tactile frames contain NaN or Inf")
    for name in ("normals", "positions", "tangents", "pad_sides_mm"):
        if not np.isfinite(getattr(batch, name)).all():
            raise DatasetError(f"sequence {name} contain NaN or Inf")
    return batch


def _geometry_spec(spec: dict) -> dict:
    return {k: v for k, v in spec.items() if k not in READOUT_SETTINGS}


def library_versions() -> dict:
    import sklearn
    import torch

    import perception

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scikit-learn": sklearn.__version__,
        "torch": torch.__version__,
        "visuotactile": getattr(perception, "__version__", "0.1.0"),
    }


class TactileClassifier(ClassifierMixin, BaseEstimator):
    """Base class; subclasses implement ``_fit(batch, y)`` and ``_predict_proba(batch) -> (S, C)``.

    Fitted attributes: ``classes_`` (names), ``sensor_spec_``, ``n_probes_``, ``grid_``.
    """

    def fit(self, X, y=None):
        """Train on ``X`` (see the module docstring); ``y``: class names or indices into ``X.class_names``.

        Raises:
            DatasetError: bad input, unknown labels, or fewer than two classes.
        """
        batch = as_batch(X)
        names = self._label_names(batch, y)
        self.classes_ = np.array(sorted(set(names.tolist())), dtype=object)
        if len(self.classes_) < 2:
            raise DatasetError(f"training data has only one class ({self.classes_[0]!r}); need at least two")
        self.sensor_spec_ = dict(batch.sensor_spec)
        self.n_probes_ = batch.n_probes
        self.grid_ = batch.grid
        y_index = np.searchsorted(self.classes_.astype(str), names.astype(str))
        self._fit(batch, y_index)
        return self

    def predict_proba(self, X) -> np.ndarray:
        """(S, C) class probabilities, columns in ``classes_`` order; rows sum to 1, all finite.

        Raises:
            ModelMismatchError: data from another sensor, probe count or taxel grid.
        """
        batch = as_batch(X)
        self.check_compatible(batch)
        proba = np.asarray(self._predict_proba(batch), dtype=np.float64)
        if not np.isfinite(proba).all():  # a defect, not bad input: say so loudly
            raise FloatingPointError(f"{type(self).__name__} produced non-finite probabilities")
        return proba / proba.sum(axis=1, keepdims=True)

    def predict(self, X) -> np.ndarray:
        """(S,) predicted class names."""
        return self.classes_[np.argmax(self.predict_proba(X), axis=1)]

    def score(self, X, y=None, sample_weight=None) -> float:
        """Accuracy on ``X`` (labels from the batch unless ``y`` is given)."""
        batch = as_batch(X)
        names = self._label_names(batch, y)
        return float(np.average(self.predict(batch).astype(str) == names.astype(str), weights=sample_weight))

    def predict_proba_touches(self, X, groups: np.ndarray, rule: str = "log") -> np.ndarray:
        """(G, C) fused probabilities of the (G, K) index ``groups`` of sequences in ``X`` (one object each)."""
        from fusion.decide import fuse_touches

        proba = self.predict_proba(X)
        return fuse_touches(proba[np.asarray(groups)], rule=rule)

    # ------------------------------------------------------------------------------ compatibility
    def check_compatible(self, batch: SequenceBatch) -> None:
        """Raise :class:`ModelMismatchError` unless ``batch`` comes from the sensor, probes and grid of training."""
        if not hasattr(self, "classes_"):
            from sklearn.exceptions import NotFittedError

            raise NotFittedError(f"{type(self).__name__} is not fitted yet; call fit first")
        ours, theirs = _geometry_spec(self.sensor_spec_), _geometry_spec(batch.sensor_spec)
        if theirs and ours != theirs:
            diff = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
            raise ModelMismatchError(
                f"{type(self).__name__} was trained on another sensor: "
                + ", ".join(f"{k} {ours.get(k)!r} (model) vs {theirs.get(k)!r} (data)" for k in diff)
                + "; record the data with the model's sensor (model.sensor()) or retrain"
            )
        if batch.n_probes != self.n_probes_ or batch.grid != tuple(self.grid_):
            raise ModelMismatchError(
                f"{type(self).__name__} was trained on {self.n_probes_} probes of {self.grid_[0]} x "
                f"{self.grid_[1]} taxels, got {batch.n_probes} probes of {batch.grid[0]} x {batch.grid[1]}"
            )

    def sensor(self) -> FSRSensor:
        """The :class:`FSRSensor` the model was trained with (to record new data for it)."""
        return FSRSensor.from_spec(self.sensor_spec_)

    @property
    def probes(self) -> int:
        return self.n_probes_

    def _label_names(self, batch: SequenceBatch, y) -> np.ndarray:
        if y is None:
            if (batch.labels < 0).any():
                raise DatasetError("some sequences have no label; pass y")
            return np.asarray(batch.class_names, dtype=object)[batch.labels]
        y = np.asarray(y)
        if len(y) != len(batch):
            raise DatasetError(f"{len(y)} labels for {len(batch)} sequences")
        if y.dtype.kind in "iu":
            if batch.class_names and ((y < 0) | (y >= len(batch.class_names))).any():
                raise DatasetError("label indices outside the batch's class list")
            return np.asarray(batch.class_names, dtype=object)[y] if batch.class_names else y.astype(str)
        return y.astype(object)

    # ------------------------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> Path:
        """Write the fitted model to ``path`` atomically (a pickle with a metadata header)."""
        if not hasattr(self, "classes_"):
            raise DatasetError(f"{type(self).__name__}: fit the model before saving it")
        header = {
            "format": MODEL_FORMAT,
            "kind": type(self).__name__,
            "classes": [str(c) for c in self.classes_],
            "sensor_spec": self.sensor_spec_,
            "probes": self.n_probes_,
            "grid": list(self.grid_),
            "cue": getattr(self, "cue", None),
            "versions": library_versions(),
        }
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            pickle.dump({"header": header, "model": self}, f, protocol=pickle.HIGHEST_PROTOCOL)
        return Path(path)


def load_model(path: str | Path) -> TactileClassifier:
    """Load a model written by :meth:`TactileClassifier.save`.

    Raises:
        DatasetError: missing file, not a visuotactile model, or a newer format.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such model file")
    try:
        with open(path, "rb") as f:
            content = pickle.load(f)
    except Exception as exc:  # unpickling garbage raises many types
        raise DatasetError(f"{path}: not a visuotactile model ({type(exc).__name__}: {exc})") from exc
    if not isinstance(content, dict) or not isinstance(content.get("model"), TactileClassifier):
        raise DatasetError(f"{path}: not a visuotactile model")
    header = content["header"]
    if header.get("format", 0) > MODEL_FORMAT:
        raise DatasetError(f"{path}: model format {header['format']} is newer than this library's {MODEL_FORMAT}")
    saved, now = header.get("versions", {}), library_versions()
    changed = {k: (saved.get(k), v) for k, v in now.items() if k != "python" and saved.get(k) != v}
    if changed:
        log.warning("%s was saved with other library versions: %s", path, changed)
    return content["model"]


__all__ = ["READOUT_SETTINGS", "TactileClassifier", "as_batch", "library_versions", "load_model"]
