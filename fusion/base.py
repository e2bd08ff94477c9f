"""What every visuotactile classifier shares: input handling, sensor compatibility, multi-touch, save / load.

A classifier takes tactile sequences as a :class:`~tactile.explore.SequenceBatch`, an opened dataset
(:func:`tactile.dataset.open_dataset`) or the path of a dataset store, with the scikit-learn interface:
``fit(X, y=None)`` (``y`` defaults to the batch's labels), ``predict_proba``, ``predict``, ``score`` and
``classes_`` (class *names*). It remembers the sensor specification, probe count and taxel grid it was
trained on and refuses data from another sensor (:class:`ModelMismatchError`); taxel noise and dead
taxels are read-out conditions, not geometry, so they may differ (that is the noise experiment).

Models are saved with :meth:`TactileClassifier.save` as a model file (``.vtm``, :mod:`fusion.modelfile`): the
arrays in a safetensors file and, as JSON in its header, the classes, sensor spec, probes, grid, cue, library
versions, training record, constructor parameters and fitted state. :func:`load_model` never unpickles: it
rebuilds the classifier from data, choosing its class among those defined in this process (every
:class:`TactileClassifier` subclass registers itself when defined; the toolkit's own are imported on demand).
Subclasses with state beyond numbers, strings, lists, dicts and numpy arrays override ``_model_state`` and
``_restore_state`` (the CNN stores its nets' state dicts, the conventional classifier its pipeline's arrays).
Old pickled models are refused unless ``trust_pickle=True`` (for files you made yourself).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import ClassVar

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin

from perception.errors import (
    DatasetError,
    InvalidArgumentError,
    ModelFileError,
    ModelMismatchError,
    NotFittedError,
    VisuotactileError,
)
from perception.limits import limit
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Sensor settings that may differ between training and use (read-out conditions, not geometry).
READOUT_SETTINGS = ("noise_std", "dead_taxel_rate")
#: Fitted attributes every classifier has; the model file stores them in its description's header fields.
BASE_FITTED = ("classes_", "sensor_spec_", "n_probes_", "grid_", "training_")
#: Attributes never saved, so that the same model saves the same bytes: what a loaded model carries about its file,
#: and how long this process took to fit it (a CNN's ``epoch_seconds_``).
UNSAVED_ATTRIBUTES = ("_source_file", "epoch_seconds_")
#: The toolkit's classifiers by the class name a model file gives, and the module that defines each (imported
#: on demand: a model file can name only classes defined in the running process or listed here).
KNOWN_CLASSES = {"fusion.cnn.CNNClassifier": "fusion.cnn",
                 "fusion.conventional.ConventionalClassifier": "fusion.conventional"}
#: Bounds on a model file's header fields (checked before anything is built from them; probes and taxels per frame
#: are also bounded by :mod:`perception.limits`).
MAX_CLASSES = 100_000
MAX_PROBES = 100_000
MAX_TAXELS = 4096
#: Longest class name (characters): names are printed on one line by ``recognize`` and in error messages.
MAX_CLASS_NAME = 200
#: The answer of a model that rejects an object (:func:`fusion.openset.decide`); no class may bear this name.
UNKNOWN = "unknown"
#: Largest coordinate (mm) a sequence may carry: positions are float32, which a kilometre from the origin holds to
#: 0.06 mm (larger numbers lose the millimetres the cues are made of, then overflow them); pads are not that large.
MAX_COORDINATE_MM = 1e6
_ATTRIBUTE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*_$|^_[A-Za-z][A-Za-z0-9_]*$")
_REGISTRY: dict[str, type] = {}


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
    for name in ("normals", "positions", "tangents", "pad_sides_mm", "plane_points", "plane_normals"):
        values = getattr(batch, name)
        if not np.isfinite(values).all():
            raise DatasetError(f"sequence {name} contain NaN or Inf{_first_object(batch, ~np.isfinite(values))}")
        if name in ("positions", "plane_points", "pad_sides_mm") and (np.abs(values) > MAX_COORDINATE_MM).any():
            where = "" if name == "pad_sides_mm" else (" from the origin (float32 positions hold no millimetres "
                                                        "there: touch the object near the origin, as load_object "
                                                        "centres it)")
            raise DatasetError(f"sequence {name} exceed {MAX_COORDINATE_MM:g} mm{where}"
                               f"{_first_object(batch, np.abs(values) > MAX_COORDINATE_MM)}")
    return batch


def _first_object(batch: SequenceBatch, bad: np.ndarray) -> str:
    """" (first in object NAME)": the object of the first sequence ``bad`` (per element) flags, for messages."""
    rows = np.flatnonzero(bad.reshape(len(bad), -1).any(axis=1))
    names = getattr(batch, "object_names", None)
    if not len(rows) or names is None or not len(names):
        return ""
    return f" (first in object {str(names[batch.object_ids[rows[0]]])[:80]!r})"


def check_class_names(names, where: str, error=DatasetError) -> list[str]:
    """``names`` (the classes of a model, sorted) checked: printable strings of 1 to :data:`MAX_CLASS_NAME`
    characters, none of them :data:`UNKNOWN` (any case: a model answering "unknown" must mean it rejects).

    Raises:
        ``error`` naming ``where``: anything else.
    """
    for name in names:
        if not isinstance(name, str) or not 1 <= len(name) <= MAX_CLASS_NAME or not name.isprintable():
            shown = repr(name)[:60]
            raise error(f"{where}: class name {shown} is not a printable name of 1 to {MAX_CLASS_NAME} characters")
        if name.strip().lower() == UNKNOWN:
            raise error(f"{where}: a class may not be named {name!r}: it is the answer of a model that rejects an "
                        "object (rename the class)")
    return list(names)


#: Parameters renamed since model files were first written: old name -> new name (applied when loading).
RENAMED_PARAMS = {"seed": "random_state"}


def class_indices(classes, names) -> np.ndarray:
    """(N,) the index of each of ``names`` in ``classes`` (sorted class names, as a model's ``classes_``).

    Raises:
        DatasetError: a name that is not one of the classes (the first few named).
    """
    classes, names = np.asarray(classes).astype(str), np.asarray(names).astype(str)
    index = np.searchsorted(classes, names)
    unknown = (index >= len(classes)) | (classes[np.minimum(index, len(classes) - 1)] != names)
    if unknown.any():
        raise DatasetError(f"labels {sorted(set(names[unknown].tolist()))[:5]} are not among the classes "
                           f"{classes.tolist()}")
    return index


def renamed_seed(options: dict, random_state, where: str):
    """``random_state``, or the value of a ``seed`` keyword in ``options`` (the name before scikit-learn's), with a
    DeprecationWarning; ``options`` must hold nothing else.

    Raises:
        TypeError: another unexpected keyword, or both ``seed`` and a non-default ``random_state``.
    """
    unknown = sorted(set(options) - {"seed"})
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword arguments {unknown}")
    if "seed" not in options:
        return random_state
    import warnings

    warnings.warn(f"{where}: 'seed' is now 'random_state'", DeprecationWarning, stacklevel=3)
    if random_state not in (0, options["seed"]):
        raise TypeError(f"{where}() got both seed={options['seed']!r} and random_state={random_state!r}")
    return options.pop("seed")


def _geometry_spec(spec: dict) -> dict:
    return {k: v for k, v in spec.items() if k not in READOUT_SETTINGS}


def library_versions() -> dict:
    """The versions a model file records and compares on loading (:func:`perception.runtime.versions`)."""
    from perception.runtime import versions

    return versions("scikit-learn", "torch")


class TactileClassifier(ClassifierMixin, BaseEstimator):
    """Base class; subclasses implement ``_fit(batch, y)`` and ``_predict_proba(batch) -> (S, C)``.

    Fitted attributes: ``classes_`` (names), ``sensor_spec_``, ``n_probes_``, ``grid_``; optionally
    ``training_``, where the model was trained (a :class:`fusion.training.TrainingRecord` as a dict, set by
    :func:`fusion.training.train_on_store`, saved with the model and read by
    :func:`fusion.training.evaluate_on_store` to test on the held-out part).
    """

    #: Parameters added after model files of this class were first written, with the value those older files
    #: were made with (a file without the parameter loads with it, so it predicts as it did).
    OLDER_FILE_PARAMS: ClassVar[dict] = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _REGISTRY[class_name(cls)] = cls

    def fit(self, X, y=None):
        """Train on ``X`` (see the module docstring); ``y``: class names or indices into ``X.class_names``.

        Raises:
            DatasetError: bad input, unknown labels, or fewer than two classes.
        """
        batch = as_batch(X)
        names = self._label_names(batch, y)
        self.__dict__.pop("calibration_", None)  # fitted for the old model: fusion.openset.calibrate again
        self.classes_ = np.array(check_class_names(sorted(set(names.tolist())), "training data"), dtype=object)
        if len(self.classes_) < 2:
            raise DatasetError(f"training data has only one class ({self.classes_[0]!r}); need at least two")
        self.sensor_spec_ = dict(batch.sensor_spec)
        self.n_probes_ = batch.n_probes
        self.grid_ = batch.grid
        y_index = class_indices(self.classes_, names)
        self._fit(batch, y_index)
        from fusion.leakage import KEY, sequence_fingerprints

        self.training_ = {KEY: sequence_fingerprints(batch)}  # what it was fitted on: leak checks (fusion.leakage)
        return self

    def predict_proba(self, X) -> np.ndarray:
        """(S, C) class probabilities, columns in ``classes_`` order; rows sum to 1, all finite. Calibrated
        when the model was calibrated (:func:`fusion.openset.calibrate`).

        Raises:
            ModelMismatchError: data from another sensor, probe count or taxel grid.
        """
        proba = self.predict_proba_uncalibrated(X)
        calibration = getattr(self, "calibration_", None)
        if calibration:
            from fusion.openset import calibrated_fusion

            proba = calibrated_fusion(calibration, proba[:, None, :])
        return proba

    def predict_proba_uncalibrated(self, X) -> np.ndarray:
        """(S, C) the classifier's own probabilities (what :meth:`predict_proba` gives before calibration)."""
        batch = as_batch(X)
        self.check_compatible(batch)
        proba = np.asarray(self._predict_proba(batch), dtype=np.float64)
        if not np.isfinite(proba).all():
            source = getattr(self, "_source_file", None)
            if source is not None:  # finite weights read from a file can still overflow: bad input
                raise ModelFileError(f"{source}: the {type(self).__name__} it holds gives non-finite probabilities "
                                     "(damaged or hostile weights)")
            raise FloatingPointError(f"{type(self).__name__} produced non-finite probabilities")  # a defect: loudly
        return proba / proba.sum(axis=1, keepdims=True)

    def predict(self, X, reject: bool = False) -> np.ndarray:
        """(S,) predicted class names; with ``reject=True`` (a calibrated model, :func:`fusion.openset.calibrate`)
        ``"unknown"`` where a sequence fits no known class (its known score is below the 1-touch threshold)."""
        if reject:
            from fusion.openset import decide

            return decide(self, X)["label"]
        proba = self.predict_proba(X)  # first: it refuses an unfitted model
        return self.classes_[np.argmax(proba, axis=1)]

    def known_score(self, X, groups=None) -> np.ndarray:
        """(G,) how well the (G, K) index ``groups`` of sequences (default: each alone) fit a known class (higher:
        better; a calibrated model's score, see :mod:`fusion.openset`)."""
        from fusion.openset import decide

        return decide(self, X, groups)["score"]

    def score(self, X, y=None, sample_weight=None) -> float:
        """Accuracy on ``X`` (labels from the batch unless ``y`` is given).

        Raises:
            DatasetError: labels of classes the model does not know (its accuracy on them would be 0 by
                construction, not a measurement).
        """
        batch = as_batch(X)
        names = self._label_names(batch, y)
        class_indices(self.classes_, names)
        return float(np.average(self.predict(batch).astype(str) == names.astype(str), weights=sample_weight))

    def predict_proba_touches(self, X, groups: np.ndarray, rule: str | None = None) -> np.ndarray:
        """(G, C) fused probabilities of the (G, K) index ``groups`` of sequences in ``X`` (one object each).
        ``rule``: see :mod:`fusion.decide`; default for a calibrated model its fitted tempered rule and confidence
        map for K touches (:func:`fusion.openset.calibrated_fusion`), else the log rule."""
        from fusion.decide import fuse_touches

        calibration = getattr(self, "calibration_", None)
        rule = rule or ("tempered" if calibration else "log")
        if calibration and rule == "tempered":  # the fitted rule and its confidence map for K touches
            from fusion.openset import calibrated_fusion

            return calibrated_fusion(calibration, self.predict_proba_uncalibrated(X)[np.asarray(groups)])
        return fuse_touches(self.predict_proba(X)[np.asarray(groups)], rule=rule)

    # ------------------------------------------------------------------------------ compatibility
    def check_compatible(self, batch: SequenceBatch) -> None:
        """Raise :class:`ModelMismatchError` unless ``batch`` comes from the sensor, probes and grid of training."""
        if not hasattr(self, "classes_"):
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
        """Write the fitted model to ``path`` atomically as a model file (``.vtm``; see :mod:`fusion.modelfile`).

        Raises:
            NotFittedError: the model is not fitted. ModelFileError: a fitted attribute that is not plain data.
        """
        from fusion.modelfile import FORMAT_NAME, FORMAT_VERSION, SUFFIX, encode, write_model_file

        if not hasattr(self, "classes_"):
            raise NotFittedError(f"{type(self).__name__}: fit the model before saving it")
        path = Path(path)
        if path.suffix == ".pkl":
            log.warning("%s: model files are no longer pickles; the suffix %s is the usual one", path, SUFFIX)
        arrays: dict[str, np.ndarray] = {}
        try:
            params = encode(self.get_params(deep=False), "params", arrays)
            state = self._model_state(arrays)
            training = encode(getattr(self, "training_", None), "training", arrays)
        except TypeError as exc:
            raise ModelFileError(f"{path}: {type(self).__name__} cannot be written to a model file ({exc})") from None
        description = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "class": class_name(type(self)),
            "classes": [str(c) for c in self.classes_],
            "sensor_spec": encode(dict(self.sensor_spec_), "sensor_spec", arrays),
            "probes": int(self.n_probes_),
            "grid": [int(g) for g in self.grid_],
            "cue": getattr(self, "cue", None),
            "versions": library_versions(),
            "training": training,
            "params": params,
            "state": state,
        }
        return write_model_file(path, description, arrays)

    def _fitted_attributes(self, exclude=()) -> dict:
        """Fitted attributes (not parameters, not the base's header fields, not ``exclude``).

        Raises:
            TypeError: an attribute that is neither a parameter nor spelled as a fitted one (``name_``).
        """
        params = set(self.get_params(deep=False))
        fitted = {k: v for k, v in vars(self).items()
                  if k not in params and k not in BASE_FITTED and k not in UNSAVED_ATTRIBUTES and k not in exclude}
        odd = [k for k in fitted if not is_fitted_name(k)]
        if odd:
            raise TypeError(f"attributes {odd} are neither parameters nor fitted attributes (name_)")
        return fitted

    def _model_state(self, arrays: dict[str, np.ndarray]) -> dict:
        """The fitted state as JSON data (numeric arrays go to ``arrays``); override for state that is not plain
        data (numbers, strings, lists, tuples, dicts, numpy arrays)."""
        from fusion.modelfile import encode

        return {"fitted": encode(self._fitted_attributes(), "fitted", arrays)}

    def _restore_state(self, state: dict, arrays: dict[str, np.ndarray], where: str) -> None:
        """Set the fitted state written by :meth:`_model_state`; raise ModelFileError naming ``where``."""
        set_fitted(self, _field(state, "fitted", dict, where), arrays, where)


def is_fitted_name(name: str) -> bool:
    """Whether ``name`` is spelled as a fitted attribute (``name_``, or private ``_name``; never ``__name``)."""
    return bool(_ATTRIBUTE.match(name)) and not name.startswith("__")


def class_name(cls: type) -> str:
    """The name a model file gives a classifier class: ``module.QualifiedName``."""
    return f"{cls.__module__}.{cls.__qualname__}"


def set_fitted(estimator, fitted, arrays: dict[str, np.ndarray], where: str, exclude=()) -> None:
    """Decode ``fitted`` (encoded attributes) and set them on ``estimator``: only names of fitted attributes
    (``name_`` or ``_name``) that are not constructor parameters.

    Raises:
        ModelFileError: a bad name or value.
    """
    from fusion.modelfile import decode

    values = decode(fitted, arrays, where)
    if not isinstance(values, dict):
        raise ModelFileError(f"{where}: the fitted state of {type(estimator).__name__} is not a mapping")
    params = set(estimator.get_params(deep=False)) if hasattr(estimator, "get_params") else set()
    for name, value in values.items():
        if not is_fitted_name(name) or name in params or name in exclude:
            raise ModelFileError(f"{where}: {type(estimator).__name__} has no fitted attribute {name[:60]!r}")
        setattr(estimator, name, value)


def _field(mapping, key: str, kind, where: str):
    value = mapping.get(key) if isinstance(mapping, dict) else None
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise ModelFileError(f"{where}: the model description lacks a valid {key!r}")
    return value


def _model_class(name, path: Path) -> type:
    """The registered classifier class ``name`` (the toolkit's own are imported from a fixed table)."""
    if not isinstance(name, str):
        raise ModelFileError(f"{path}: the model description names no classifier class")
    if name not in _REGISTRY and name in KNOWN_CLASSES:
        import importlib

        importlib.import_module(KNOWN_CLASSES[name])
    if name not in _REGISTRY:
        raise ModelFileError(
            f"{path}: the model is a {name[:120]!r}, a class not defined in this process; import the module that "
            "defines it before loading (a model file never imports code)"
        )
    return _REGISTRY[name]


def _check_header(description: dict, path: Path) -> tuple[list[str], dict, int, tuple[int, int]]:
    """(classes, sensor spec, probes, grid) of a model description, checked."""
    from fusion.modelfile import decode

    classes = _field(description, "classes", list, path)
    if not 2 <= len(classes) <= MAX_CLASSES or not all(isinstance(c, str) for c in classes) or (
            len(set(classes)) != len(classes)):
        raise ModelFileError(f"{path}: the model's classes must be 2 to {MAX_CLASSES} distinct names")
    check_class_names(classes, f"{path}: the model", ModelFileError)
    if classes != sorted(classes):  # class_indices and every column of the model's probabilities assume the order
        raise ModelFileError(f"{path}: the model's classes are not in sorted order (damaged or hand-edited)")
    spec = decode(description.get("sensor_spec"), {}, str(path))
    if not isinstance(spec, dict):
        raise ModelFileError(f"{path}: the model description lacks a sensor specification")
    try:
        FSRSensor.from_spec(spec)
    except (VisuotactileError, TypeError, ValueError, KeyError) as exc:
        raise ModelFileError(f"{path}: the model's sensor specification is invalid ({exc})") from None
    probes = _field(description, "probes", int, path)
    grid = _field(description, "grid", list, path)
    most_probes = min(MAX_PROBES, limit("probes"))
    if not 1 <= probes <= most_probes:
        raise ModelFileError(f"{path}: {probes} probes in the model, outside 1..{most_probes} (VISUOTACTILE_MAX_PROBES)")
    if len(grid) != 2 or not all(isinstance(g, int) and not isinstance(g, bool) and 1 <= g <= MAX_TAXELS
                                 for g in grid):
        raise ModelFileError(f"{path}: bad taxel grid {str(grid)[:40]} in the model (two integers 1..{MAX_TAXELS})")
    if grid[0] * grid[1] > limit("taxels"):
        raise ModelFileError(f"{path}: a {grid[0]} x {grid[1]} taxel grid in the model is above the limit of "
                             f"{limit('taxels')} taxels per frame (set VISUOTACTILE_MAX_TAXELS to raise it)")
    if "rows" in spec and (spec.get("rows"), spec.get("cols")) != tuple(grid):
        raise ModelFileError(f"{path}: the model's taxel grid {grid} differs from its sensor's")
    return classes, spec, probes, (grid[0], grid[1])


def load_model(path: str | Path, *, trust_pickle: bool = False, max_bytes: int | None = None) -> TactileClassifier:
    """Load a model written by :meth:`TactileClassifier.save`; nothing in the file is executed.

    Args:
        trust_pickle: also load an old pickled model (visuotactile before model files); unpickling runs any
            code the file holds, so only for files you made yourself.
        max_bytes: largest file accepted (default :data:`fusion.modelfile.MAX_MODEL_BYTES`).

    Raises:
        ModelFileError: missing file, a pickle (without ``trust_pickle``), not a visuotactile model, damaged,
            truncated or inconsistent, or a newer format. InvalidArgumentError: ``path`` is not a path.
    """
    from fusion.modelfile import MAX_MODEL_BYTES, decode, looks_like_pickle, read_model_file

    if not isinstance(path, (str, os.PathLike)):
        raise InvalidArgumentError(f"load_model: expected a model file path, got {type(path).__name__}")
    path = Path(path)
    if trust_pickle and path.is_file():
        with open(path, "rb") as f:
            if looks_like_pickle(f.read(9)):
                return _load_pickle(path)
    description, arrays = read_model_file(path, MAX_MODEL_BYTES if max_bytes is None else max_bytes)
    cls = _model_class(description.get("class"), path)
    classes, spec, probes, grid = _check_header(description, path)
    params = decode(_field(description, "params", dict, path), arrays, str(path))
    names = set(cls._get_param_names())
    params = {RENAMED_PARAMS.get(k, k) if k not in names else k: v for k, v in params.items()}
    params = {**cls.OLDER_FILE_PARAMS, **params}
    unknown = sorted(set(params) - names)
    if unknown:
        raise ModelFileError(f"{path}: {cls.__name__} has no parameters {unknown[:5]}")
    from fusion.leakage import check_training_record

    training = check_training_record(decode(description.get("training"), arrays, str(path)), str(path))
    try:
        model = cls(**params)
        model.classes_ = np.array(classes, dtype=object)
        model.sensor_spec_, model.n_probes_, model.grid_ = spec, probes, grid
        if training is not None:
            model.training_ = training
        model._restore_state(_field(description, "state", dict, path), arrays, str(path))
        model._source_file = str(path)  # names the file when its numbers misbehave (not saved, not a parameter)
        if hasattr(model, "calibration_"):
            from fusion.openset import check_calibration, embedding_width

            model.calibration_ = check_calibration(model.calibration_, len(classes), str(path),
                                                   embedding_width(model))
    except ModelFileError:
        raise
    except VisuotactileError as exc:  # e.g. a parameter the classifier's own checks refuse
        raise ModelFileError(f"{path}: inconsistent model ({exc})") from None
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, RuntimeError) as exc:
        raise ModelFileError(f"{path}: inconsistent model ({type(exc).__name__}: {str(exc)[:200]})") from None
    saved, now = description.get("versions"), library_versions()
    if isinstance(saved, dict):
        changed = {k: (saved.get(k), v) for k, v in now.items() if k != "python" and saved.get(k) != v}
        if changed:
            log.warning("%s was saved with other library versions: %s", path, changed)
    return model


def _load_pickle(path: Path) -> TactileClassifier:
    """An old pickled model (``trust_pickle=True`` only: this runs whatever code the file holds)."""
    import pickle

    log.warning("%s: unpickling a model file (trust_pickle=True); save it again to get the safe format", path)
    try:
        with open(path, "rb") as f:
            content = pickle.load(f)  # the caller vouched for this file
    except Exception as exc:  # noqa: BLE001 -- unpickling garbage raises many types
        raise ModelFileError(f"{path}: not a visuotactile model ({type(exc).__name__}: {exc})") from None
    if not isinstance(content, dict) or not isinstance(content.get("model"), TactileClassifier):
        raise ModelFileError(f"{path}: not a visuotactile model")
    return content["model"]


__all__ = ["READOUT_SETTINGS", "RENAMED_PARAMS", "TactileClassifier", "as_batch", "class_indices", "class_name", "is_fitted_name", "library_versions",
           "load_model", "set_fitted"]
