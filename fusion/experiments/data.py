"""Which objects each experiment uses, and the dataset stores it reads (generated once, cached, resumed).

Stores live in ``<report>/stores/<name>.zarr`` and are made by :func:`tactile.dataset.generate`, which
resumes an interrupted generation and refuses a store made with other settings.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

from perception.errors import DatasetError, InvalidArgumentError
from tactile.dataset.objects import ObjectSpec
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Sub-folder of a stores folder that keeps the objects' interest points, shared by all its stores.
SALIENCY_CACHE = "interest-points"


def folder_objects(folder: str | Path, classes=None, per_class: int | None = None,
                   max_classes: int | None = None) -> list[tuple[Path, str]]:
    """(path, class) pairs of a class-per-folder mesh set: the named ``classes`` (default: all, or the first
    ``max_classes`` in sorted order), each with its first ``per_class`` files in sorted order (default all).

    Byte-identical files count as one object (the first in sorted order is kept, the others are logged and left
    out), so no split can put a copy of a test object in training.

    Raises:
        DatasetError: a bad folder (see :func:`perception.geometry.list_collection`), an unknown class, or a
            class with fewer than ``per_class`` files.
        InvalidArgumentError: ``per_class`` below 1.
    """
    from perception.geometry import list_collection

    if per_class is not None and (isinstance(per_class, bool) or int(per_class) != per_class or per_class < 1):
        raise InvalidArgumentError(f"objects per class must be an integer >= 1, got {per_class!r}")

    listed = list_collection(folder)
    # copies are found across every class (a file in two class folders is one object), warned about in the asked ones
    asked = set(classes) if classes else set(sorted({label for _, label in listed})[:max_classes or None])
    items = unique_meshes(listed, warn_labels=asked)
    available = sorted({label for _, label in items})
    if classes:
        unknown = [c for c in classes if c not in available]
        if unknown:
            raise DatasetError(f"{folder}: no class folders {unknown}; the classes are {', '.join(available)}")
        chosen = list(dict.fromkeys(classes))
    else:
        chosen = available[:max_classes] if max_classes else available
    out = []
    for label in chosen:
        files = [path for path, lab in items if lab == label]
        if per_class is not None and len(files) < per_class:
            raise DatasetError(f"{folder}/{label}: {len(files)} meshes, fewer than the {per_class} asked for")
        out += [(path, label) for path in files[:per_class]]
    return out


def mesh_digest(path: str | Path) -> str:
    """SHA-256 of a mesh file's bytes: equal digests, one object."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


#: (duplicate, original) pairs already warned about: every part of a run lists the objects again.
_WARNED: set[tuple[str, str]] = set()


def unique_meshes(items: list[tuple[Path, str]], warn_labels=None) -> list[tuple[Path, str]]:
    """``items`` without the files whose bytes (SHA-256) equal an earlier one's (logged as a warning, once per
    process and pair, when the copy's class is in ``warn_labels``; None: any)."""
    seen: dict[str, Path] = {}
    out = []
    for path, label in items:
        key = mesh_digest(path)
        if key in seen:
            pair = (str(path), str(seen[key]))
            if pair not in _WARNED and (warn_labels is None or label in warn_labels):
                _WARNED.add(pair)
                log.warning("%s is byte-identical to %s: counted as one object", *pair)
            continue
        seen[key] = Path(path)
        out.append((path, label))
    return out


def any_pose(objects, seed: int) -> list:
    """The same objects as :class:`~tactile.dataset.ObjectSpec` s, each turned by its own uniformly random
    rotation (applied to the raw mesh before loading), drawn from (``seed``, object name): the "any pose"
    setting of the experiments. Same seed, same poses."""
    from tactile.dataset import object_specs
    from tactile.dataset.store import contour_seed

    return [ObjectSpec(**{**vars(spec), "rotation_seed": contour_seed(seed, spec.name, "pose", 0)})
            for spec in object_specs(objects)]


def catalogue_objects(classes, per_class: int, first_seed: int = 0) -> list[tuple[str, int]]:
    """(class, seed) pairs of the built-in catalogue: seeds ``first_seed .. first_seed + per_class - 1``.

    Raises:
        InvalidArgumentError: a class not in the catalogue, or ``per_class`` below 1.
    """
    from perception.shapes import CLASSES

    unknown = sorted(set(classes) - set(CLASSES))
    if unknown:
        raise InvalidArgumentError(f"unknown catalogue classes {unknown}; the built-in classes are {', '.join(CLASSES)}")
    if isinstance(per_class, bool) or int(per_class) != per_class or per_class < 1:
        raise InvalidArgumentError(f"the catalogue needs at least 1 object per class, got {per_class!r}")
    from perception.limits import check_count

    check_count("objects", len(classes) * int(per_class), f"the catalogue: {len(classes)} classes x {per_class} objects")
    return [(c, first_seed + i) for c in classes for i in range(per_class)]


def store_record(objects, contours: int, seed: int, strategies=("guided", "blind"), sensor: FSRSensor | None = None,
                 probes: int = 25) -> dict:
    """What identifies a store's content (its name and the cache records of models trained on it use it): the
    settings and the code that generates the rows (:func:`tactile.dataset.generation_code_version`), so a folder's
    store made by other code is not read as this code's."""
    from tactile.dataset import generation_code_version, object_specs
    from tactile.sampling import pair_setting

    strategies = [strategies] if isinstance(strategies, str) else list(strategies)
    return {"objects": [_identity(spec) for spec in object_specs(objects)], "contours": contours, "seed": seed,
            "strategies": strategies, "sensor": (sensor or FSRSensor()).spec(), "probes": probes,
            **pair_setting(strategies), "generation_code": generation_code_version()}


def _identity(spec) -> list:
    """[path or catalogue item, label] (the record format of upright objects), plus the pose seed if any. An object
    made by a loader is its name, function and arguments: the function alone is the same for a whole set of
    loaded objects (say, every virtual capture), whose stores would otherwise share one name."""
    if spec.path is not None:
        source = str(spec.path)
    elif spec.catalogue is not None:
        source = str(tuple(spec.catalogue))
    else:
        identity = spec.to_dict()
        source = f"{identity['name']} = {identity['loader']}{identity.get('loader_args', '')}"
    return [source, spec.label] + ([spec.rotation_seed] if spec.rotation_seed is not None else [])


def ensure_store(objects, folder: Path, *, strategies, contours: int, seed: int, sensor: FSRSensor | None = None,
                 probes: int = 25, workers: int | None = None, progress: bool = True) -> tuple:
    """Generate (or resume, or reuse) the store of these settings in ``folder`` and open it.

    The store is named after its settings (``<objects>obj-<contours>c-<hash>.zarr``), so parts that need
    the same data share one store and changed sizes make a new one. Objects that fail to generate are logged
    and left out (``generate`` records them); re-running tries them again. The stores of one folder share
    an interest-point cache (``folder/interest-points``), so each object's saliency is computed once.

    Returns:
        (the opened dataset, its :func:`store_record`).

    Raises:
        DatasetError: every object failed.
    """
    from fusion.experiments.models import digest
    from tactile.dataset import generate, open_dataset

    record = store_record(objects, contours, seed, strategies, sensor, probes)
    path = Path(folder) / f"{len(record['objects'])}obj-{contours}c-{digest(record)[:10]}.zarr"
    report = generate(objects, path, strategies=tuple(strategies), contours_per_object=contours,
                      sensor=sensor or FSRSensor(), probes=probes, seed=seed, workers=workers, progress=progress,
                      saliency_cache=Path(folder) / SALIENCY_CACHE)
    for name, reason in report.failed:
        log.warning("%s: object %s failed and is left out: %s", path.name, name, reason)
    if report.failed and len(report.failed) == report.objects:
        raise DatasetError(f"{path}: every object failed to generate (first: {report.failed[0]})")
    return open_dataset(path), record


def load_models(objects) -> list:
    """The :class:`~perception.geometry.ObjectModel` of each object spec (same names and labels as the stores)."""
    from tactile.dataset import object_specs

    return [spec.load() for spec in object_specs(objects)]


def split_loader(ds, train, test, test_ds=None):
    """``load("train" | "test")``: the split's batch, read from the store once and only when asked for (the
    test indices from ``test_ds`` when given)."""
    cache: dict = {}

    def load(which: str):
        if which not in cache:
            cache[which] = ds.load(train) if which == "train" else (test_ds or ds).load(test)
        return cache[which]

    return load


__all__ = [
    "any_pose",
    "catalogue_objects",
    "ensure_store",
    "folder_objects",
    "load_models",
    "mesh_digest",
    "split_loader",
    "store_record",
    "unique_meshes",
]
