"""Which classifiers the experiments train, and training / predicting with a cache in the report folder.

A trained model is saved next to a small JSON record of what it was trained on (classifier parameters, data,
training indices); a re-run with the same record loads it instead of training again, so an interrupted run
resumes and a finished one is cheap to re-report. Models are cached as model files (``.vtm``: safetensors and
JSON, :mod:`fusion.modelfile`; loading one runs no code, so a report folder from elsewhere is safe to resume);
predictions are cached the same way (``.npz``, read without pickles).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import joblib
import numpy as np

from fusion.base import TactileClassifier, load_model
from fusion.modelfile import SUFFIX
from perception.atomic import atomic_path, write_text
from perception.errors import DatasetError, InvalidArgumentError, ModelMismatchError
from perception.runtime import usable_cores
from tactile.explore import SequenceBatch

log = logging.getLogger(__name__)

Factory = Callable[[], TactileClassifier]

#: Display names of the classifiers and of the CNN's single modalities. Plain names use the pose-free cues;
#: ``-normals`` names the paper's kinesthetic cue (surface normals in the object's stored frame).
DISPLAY = {"cnn": "CNN fusion", "svm": "SVM", "knn": "kNN", "cnn-normals": "CNN fusion (normals cue)",
           "svm-normals": "SVM (normals cue)", "knn-normals": "kNN (normals cue)"}
MODALITY_DISPLAY = {"cutaneous": "CNN cutaneous", "kinesthetic": "CNN kinesthetic"}


#: Frame side (taxels) the paper's CNN pair pools to (the pose-free pair keeps ``CNNClassifier``'s 16). Chosen inside
#: the paper protocol's training part (blind SHREC paper store, its training sequences split again 80/20, the test
#: sequences unread; rule set before the fits: take 8 unless its fusion accuracy falls by more than 0.2 points):
#: fusion 99.84 % at both sizes on 3,648 sequences, paired 0.0 [-0.16, +0.16] points, cutaneous alone 97.2 against
#: 96.8 %, fits of 246 against 382 s on one core. Chosen on blind contours, it serves every ``cnn-normals`` model
#: (the paper part's guided pair too: 100 % on its test sequences at either size, README). The same question for
#: the pose-free pair (nested grouped 3-fold inside the unseen-objects folds) answered no: see the ``fusion.cnn``
#: module docstring.
PAPER_FRAME_SIZE = 8


def default_classifiers(seed: int = 0, epochs: int | None = None, progress: bool = False,
                        threads: int | None = None) -> dict[str, Factory]:
    """Factories of the toolkit's classifiers by name: ``cnn`` (CNN pair), ``svm``, ``knn`` (contourlet +
    wavelet features), all with the pose-free kinesthetic cues, and the same with the paper's normals cue
    (``cnn-normals``, ``svm-normals``, ``knn-normals``), which depends on how each object is posed; the paper's CNN
    pair sums its nets' probabilities and pools its frames to :data:`PAPER_FRAME_SIZE` taxels a side.

    ``threads``: the CNNs' CPU threads (None: the cores of the process that trains them). A fixed count makes the
    trained weights the same bytes on any machine (the kernels' sums depend on it); ``reproduce`` uses 1 and
    trains several models side by side (:mod:`fusion.experiments.parallel`).
    """
    from fusion.classifiers import make_classifier

    cnn = ({"epochs": epochs} if epochs else {}) | ({"threads": threads} if threads else {})
    factories = {}
    for cue, suffix in (("invariant", ""), ("normals", "-normals")):
        # the paper's models sum the two nets and pool their frames to PAPER_FRAME_SIZE
        rule = {"modality_rule": "sum", "frame_size": PAPER_FRAME_SIZE} if cue == "normals" else {}
        factories[f"cnn{suffix}"] = functools.partial(make_classifier, "cnn", cue=cue, random_state=seed, progress=progress,
                                                      **cnn, **rule)
        # the paper's models keep the paper's pipeline; the pose-free ones choose theirs on the training objects
        search = {"search": None} if cue == "normals" else {}
        for kind in ("svm", "knn"):
            factories[f"{kind}{suffix}"] = functools.partial(make_classifier, kind, cue=cue, random_state=seed,
                                                             **search)
    return factories


def pick(classifiers: dict[str, Factory], names) -> dict[str, Factory]:
    """The factories named in ``names`` (in that order).

    Raises:
        InvalidArgumentError: a name that is not available.
    """
    missing = [n for n in names if n not in classifiers]
    if missing:
        raise InvalidArgumentError(f"unknown classifiers {missing}; available: {', '.join(classifiers)}")
    return {n: classifiers[n] for n in names}


def digest(*parts) -> str:
    """A short stable hash of JSON-able parts (arrays by their bytes)."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def write_cache(path: str | Path, meta: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write a cache file atomically: an ``.npz`` of ``arrays`` and their ``meta`` (JSON, one string entry)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, meta=np.array(json.dumps(meta, default=str)), **arrays)
    return Path(path)


def read_cache(path: str | Path, field: str, key, read: Callable):
    """``read(meta, data)`` of the cache file at ``path`` (:func:`write_cache`; ``data``: the open ``.npz``), or
    None when it is absent, unreadable (logged), or its ``meta[field]`` is not ``key`` (after the same JSON
    round trip; ``key=None``: any)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if not isinstance(meta, dict):
                raise DatasetError("its meta is not a JSON object")
            if key is not None and meta.get(field) != json.loads(json.dumps(key, default=str)):
                log.info("%s was made with other settings; making it again", path)
                return None
            return read(meta, data)
    # A file cut short is BadZipFile; a meta that is no JSON object and arrays that do not fit together (a damaged
    # file) are DatasetError; a meta field of the wrong type makes read raise TypeError.
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, DatasetError) as exc:
        log.warning("%s is unreadable (%s); making it again", path, exc)
        return None


#: Modules that only use a fitted model's outputs (fusing, calibrating, scoring its probabilities; calibration is
#: fitted outside the cache): never part of a classifier's code version, nor followed for imports.
NOT_MODEL_CODE = frozenset({"fusion.decide", "fusion.evaluate", "fusion.calibration", "fusion.openset"})


def _source_text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _module_file(name: str) -> Path | None:
    """The source file of module ``name`` of the ``fusion`` package (a package: its ``__init__.py``), or None."""
    root = Path(__file__).resolve().parents[2]
    base = root.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _fusion_imports(source: str, module: str, is_package: bool) -> set[str]:
    """Names of the ``fusion`` modules a source imports (at any depth: top level and inside functions)."""
    import ast

    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the module's package
                parts = module.split(".")[:len(module.split(".")) - node.level + is_package]
                origin = ".".join(parts + ([node.module] if node.module else []))
            else:
                origin = node.module or ""
            names.add(origin)
            names.update(f"{origin}.{alias.name}" for alias in node.names)  # `from package import module`
    return {n for n in names if n == "fusion" or n.startswith("fusion.")}


def model_code_files(cls: type) -> list[Path]:
    """The files a classifier's code lives in: the modules of ``cls`` and of its base classes that belong to
    ``fusion`` (or are ``cls``'s own), and every ``fusion`` module they import, transitively (imports read from
    the source), but :data:`NOT_MODEL_CODE`. For CNNClassifier, say: fusion/cnn.py, base.py, cues.py, leakage.py,
    modelfile.py; not fusion/demo.py, the commands or the experiments."""
    starts = [cls.__module__] + [c.__module__ for c in cls.__mro__[1:] if c.__module__.split(".")[0] == "fusion"]
    return _code_files(starts, cls, NOT_MODEL_CODE)


def _code_files(starts: list[str], cls: type | None, skip: frozenset) -> list[Path]:
    """The source files of the ``fusion`` modules ``starts`` (and of ``cls``'s own module) and of every ``fusion``
    module they import, transitively, but those in ``skip``."""
    seen, files, todo = set(), {}, list(dict.fromkeys(starts))
    while todo:
        name = todo.pop()
        if name in seen or name in skip:
            continue
        seen.add(name)
        path = _module_file(name) if name.split(".")[0] == "fusion" else None
        if path is None and cls is not None and name == cls.__module__:  # a classifier defined outside fusion (a test's stand-in)
            import inspect

            try:
                found = inspect.getsourcefile(cls)
            except (TypeError, OSError):  # defined interactively: only its fusion modules count
                found = None
            path = Path(found).resolve() if found else None
        if path is None:
            continue
        files[name] = path
        todo.extend(_fusion_imports(_source_text(path), name, path.name == "__init__.py"))
    return sorted(files.values())


#: Libraries a classifier's fit and outputs depend on: a model cached under another version of one is trained again.
MODEL_LIBRARIES = ("scipy", "scikit-learn", "torch", "PyWavelets")


@functools.cache
def model_code_version(cls: type) -> str:
    """A hash of the code of classifier class ``cls`` (the files of :func:`model_code_files`): a cached model
    trained by other code is trained again, while an edit to a module the classifier does not use (the demo,
    the commands, the experiments, :data:`NOT_MODEL_CODE`) keeps cached models valid. The versions of numpy and
    :data:`MODEL_LIBRARIES` are part of it: another PyTorch or scikit-learn trains again. Read once per process and
    class: the code that runs is the code that was imported, whatever happens to the files during a long run."""
    return _files_version(model_code_files(cls))


@functools.cache
def calibration_code_version() -> str:
    """A hash of the code :func:`fusion.openset.calibrate` runs beyond the classifier's own (:mod:`fusion.openset`,
    :mod:`fusion.calibration`, :mod:`fusion.decide` and what they import) and of the library versions: a model
    calibrated by other code is calibrated again. Read once per process, as :func:`model_code_version`."""
    return _files_version(_code_files(["fusion.openset"], None, frozenset()))


def _files_version(files: list[Path]) -> str:
    from perception.runtime import versions

    root = Path(__file__).resolve().parents[2]
    return digest(*[f"{p.relative_to(root) if p.is_relative_to(root) else p.name}:{_source_text(p)}" for p in files],
                  sorted(versions(*MODEL_LIBRARIES).items()))


def describe(estimator: TactileClassifier) -> str:
    """The estimator's class, parameters and code version (part of the cache record)."""
    params = {k: v for k, v in estimator.get_params(deep=False).items() if k != "progress"}
    return (f"{type(estimator).__name__}({json.dumps(params, sort_keys=True, default=str)}) "
            f"code {model_code_version(type(estimator))}")


def fit_cached(factory: Factory, train, path: Path, record: dict) -> tuple[TactileClassifier, float]:
    """Train ``factory()`` on ``train`` (a batch, or a callable returning one, called only when training is
    needed), or load the model saved at ``path`` if it was trained with the same ``record``. ``record`` must
    identify the training data (store and indices); the estimator's parameters are added here.

    Returns the model and its training time in seconds (as measured when it was trained).
    """
    full_record = model_record(factory, record)
    cached = load_cached(path, full_record)
    if cached is not None:
        return cached
    estimator = factory()
    batch = train() if callable(train) else train
    start = time.perf_counter()
    # scikit-learn steps left at n_jobs=None (the SVM's calibration folds) use every core while training; nothing
    # else runs then, and their results do not depend on the job count.
    with joblib.parallel_config(n_jobs=usable_cores()):
        estimator.fit(batch)
    seconds = time.perf_counter() - start
    save_fitted(estimator, seconds, path, full_record)
    return estimator, seconds


def model_record(factory: Factory, record: dict) -> dict:
    """The record a model trained by ``factory()`` on the data ``record`` names is cached with: ``record`` and
    the estimator's class, parameters and code version, as JSON reads it back."""
    return json.loads(json.dumps({**record, "estimator": describe(factory())}, default=str))


def load_cached(path: Path, full_record: dict) -> tuple[TactileClassifier, float] | None:
    """The model saved at ``path`` with ``full_record`` (:func:`save_fitted`) and its training seconds; None when
    there is none, it was saved with another record, or it cannot be loaded (then with a warning: make it again)."""
    seconds = cached_fit_seconds(path, full_record)
    if seconds is None:
        return None
    try:
        return load_model(path), seconds
    except (DatasetError, ModelMismatchError, OSError, ValueError) as exc:
        log.warning("cached model %s unusable (%s); making it again", path, exc)
        return None


def cached_fit_seconds(path: Path, full_record: dict) -> float | None:
    """The training seconds saved with the model at ``path`` when it was saved with ``full_record``
    (:func:`model_record`), else None; reads only its JSON."""
    meta_path = path.with_suffix(".json")
    if not (path.is_file() and meta_path.is_file()):
        return None
    try:
        meta = json.loads(meta_path.read_text())
        return float(meta["fit_seconds"]) if meta.get("record") == full_record else None
    except (OSError, ValueError, AttributeError, KeyError, TypeError) as exc:
        log.warning("cached model record %s unusable (%s); training again", meta_path, exc)
        return None


def save_fitted(estimator: TactileClassifier, fit_seconds: float, path: Path, full_record: dict) -> None:
    """Save a fitted ``estimator`` at ``path`` with its record (:func:`model_record`) and training time, where
    :func:`fit_cached` finds it (the model first: a record never names a model that is not there; the old record
    goes before the model is replaced, so an interrupt in between never pairs it with the new model)."""
    path.with_suffix(".json").unlink(missing_ok=True)
    estimator.save(path)
    write_text(path.with_suffix(".json"), json.dumps({"record": full_record, "fit_seconds": fit_seconds}, indent=2,
                                                     default=str))


@dataclass
class Predictions:
    """Class probabilities of one model on one test set, with what is needed to score them.

    Attributes:
        proba: (S, C) probabilities, columns in ``classes`` order.
        labels: (S,) true class names.
        object_ids: (S,) object of each sequence (an index into ``object_names``).
        classes, object_names: name lists.
        modalities: single-modality (S, C) probabilities (CNN: cutaneous, kinesthetic).
        fit_seconds: training time; predict_seconds: inference time per sequence (batch inference).
    """

    proba: np.ndarray
    labels: np.ndarray
    object_ids: np.ndarray
    classes: list[str]
    object_names: list[str]
    modalities: dict[str, np.ndarray] = field(default_factory=dict)
    fit_seconds: float = 0.0
    predict_seconds: float = 0.0

    @property
    def predicted(self) -> np.ndarray:
        return np.asarray(self.classes, dtype=object)[np.argmax(self.proba, axis=1)]

    def modality(self, name: str) -> Predictions:
        """The same predictions with ``proba`` of one modality."""
        return Predictions(self.modalities[name], self.labels, self.object_ids, self.classes, self.object_names,
                           {}, self.fit_seconds, self.predict_seconds)

    @staticmethod
    def concatenate(parts: list[Predictions]) -> Predictions:
        """Stack predictions of several folds (same classes and object list)."""
        if not parts:
            raise DatasetError("no predictions to concatenate")
        first = parts[0]
        keys = set.intersection(*(set(p.modalities) for p in parts))
        return Predictions(
            np.concatenate([p.proba for p in parts]), np.concatenate([p.labels for p in parts]),
            np.concatenate([p.object_ids for p in parts]), first.classes, first.object_names,
            {k: np.concatenate([p.modalities[k] for p in parts]) for k in sorted(keys)},
            float(sum(p.fit_seconds for p in parts) / len(parts)),
            float(np.mean([p.predict_seconds for p in parts])),
        )

    def save(self, path: Path, record: dict) -> None:
        meta = {"classes": self.classes, "object_names": self.object_names, "fit_seconds": self.fit_seconds,
                "predict_seconds": self.predict_seconds, "record": record}
        arrays = {"proba": self.proba, "labels": self.labels.astype(str), "object_ids": self.object_ids}
        arrays |= {f"modality_{k}": v for k, v in self.modalities.items()}
        write_cache(path, meta, arrays)

    @classmethod
    def load(cls, path: Path, record: dict) -> Predictions | None:
        def read(meta, data):
            modalities = {k[len("modality_"):]: data[k] for k in data.files if k.startswith("modality_")}
            return cls(data["proba"], data["labels"].astype(object), data["object_ids"], meta["classes"],
                       meta["object_names"], modalities, meta["fit_seconds"], meta["predict_seconds"])

        return read_cache(path, "record", record, read)


def predict(model: TactileClassifier, test: SequenceBatch, fit_seconds: float = 0.0) -> Predictions:
    """Predict ``test`` with ``model`` (timed), keeping the CNN's single-modality outputs when it has them."""
    start = time.perf_counter()
    modalities = {}
    if hasattr(model, "predict_proba_modalities"):
        outputs = model.predict_proba_modalities(test)
        proba = np.asarray(outputs["fusion"], dtype=np.float64)
        modalities = {k: np.asarray(v, dtype=np.float64) for k, v in outputs.items() if k != "fusion"}
    else:
        proba = model.predict_proba(test)
    seconds = (time.perf_counter() - start) / max(len(test), 1)
    if not all(np.isfinite(p).all() for p in (proba, *modalities.values())):
        raise FloatingPointError(f"{type(model).__name__} produced non-finite probabilities")
    labels = np.asarray(test.class_names, dtype=object)[test.labels]
    return Predictions(proba, labels, np.asarray(test.object_ids), [str(c) for c in model.classes_],
                       list(test.object_names), modalities, fit_seconds, seconds)


def train_and_predict(name: str, factory: Factory, train, test, folder: Path, record: dict,
                      test_record: dict | None = None) -> Predictions:
    """Train (or load) classifier ``name`` and predict ``test`` (or load the cached predictions); the model
    goes to ``folder/name.vtm``, the predictions to ``folder/name[-tag].npz``.

    Args:
        train, test: batches, or callables returning them (called only when needed).
        record: identifies the training data (see :func:`fit_cached`).
        test_record: identifies the test data; its ``"tag"`` (default "test") names the predictions file.
    """
    cached = cached_predictions(name, factory, folder, record, test_record)
    if cached is not None:
        return cached
    model, fit_seconds = fit_cached(factory, train, folder / f"{name}{SUFFIX}", record)
    result = predict(model, test() if callable(test) else test, fit_seconds)
    result.save(*_predictions_file(name, factory, folder, record, test_record))
    return result


def cached_predictions(name: str, factory: Factory, folder: Path, record: dict,
                       test_record: dict | None = None) -> Predictions | None:
    """The predictions :func:`train_and_predict` would load from its cache with these arguments, or None."""
    if not (folder / f"{name}{SUFFIX}").is_file():
        return None
    return Predictions.load(*_predictions_file(name, factory, folder, record, test_record))


def _predictions_file(name: str, factory: Factory, folder: Path, record: dict,
                      test_record: dict | None) -> tuple[Path, dict]:
    """Where :func:`train_and_predict` caches its predictions, and the record they are saved with."""
    test_record = test_record or {"tag": "test"}
    estimator_record = {**record, "estimator": describe(factory()), "test": test_record}
    return (folder / f"{name}-{test_record.get('tag', 'test')}.npz",
            json.loads(json.dumps(estimator_record, default=str)))


__all__ = ["DISPLAY", "MODALITY_DISPLAY", "MODEL_LIBRARIES", "PAPER_FRAME_SIZE", "Predictions", "cached_fit_seconds", "cached_predictions",
           "default_classifiers", "digest", "fit_cached", "model_record", "pick", "predict", "save_fitted",
           "train_and_predict"]
