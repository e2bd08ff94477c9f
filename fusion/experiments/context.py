"""What every part of an experiment run shares: the report folder, seed, sizes, classifiers, progress."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from fusion.experiments.config import Sizes
from fusion.experiments.models import Factory, digest
from perception.atomic import write_text

log = logging.getLogger(__name__)


@dataclass
class Context:
    """One experiment run.

    Attributes:
        out: the report folder (stores, models, predictions and per-part results are cached under it).
        seed: the run's seed (stores, splits, classifiers, bootstraps).
        sizes: :class:`Sizes` of the parts.
        classifiers: name -> factory of an unfitted classifier.
        progress: tqdm bars.
        workers: worker processes of store generation and of model fits (None: the usable cores).
        timings: wall seconds of each part in this process (not cached: they say how long *this* run took).
        stores: the stores this run has generated or checked, by their record's digest (:meth:`store`): each is
            verified and opened once per run, however many parts read it.
        outliers: objects of no class of the run ((mesh path, label) or (catalogue class, seed) pairs) whose touches
            the calibration and open-set parts' CNNs train on with outlier exposure (None: none).
    """

    out: Path
    seed: int
    sizes: Sizes
    classifiers: dict[str, Factory]
    progress: bool = True
    workers: int | None = None
    timings: dict[str, float] = field(default_factory=dict)
    stores: dict[str, tuple] = field(default_factory=dict)
    outliers: list | None = None

    def path(self, *parts: str) -> Path:
        return self.out.joinpath(*parts)

    def cached_part(self, name: str, record: dict, compute: Callable[[], dict]) -> dict:
        """The JSON result of part ``name``: from ``parts/<name>.json`` when made with the same ``record`` and the
        same generation code (:func:`tactile.dataset.generation_code_version`: a part computed on stores of other
        code is computed again; measured timings are kept, so a re-run reports the same numbers), else ``compute()``
        saved there."""
        saved = self._saved_part(name, record)
        if saved is not None:
            return saved
        result = compute()
        write_text(self.path("parts", f"{name}.json"),
                   json.dumps({"key": _part_key(record), "record": record, "result": result}, indent=2, default=str))
        return result

    def has_part(self, name: str, record: dict) -> bool:
        """Whether :meth:`cached_part` would read part ``name`` made with ``record`` instead of computing it."""
        return self._saved_part(name, record) is not None

    def _saved_part(self, name: str, record: dict) -> dict | None:
        path = self.path("parts", f"{name}.json")
        if path.is_file():
            try:
                saved = json.loads(path.read_text())
                if saved.get("key") == _part_key(record):
                    return saved["result"]
            except (OSError, ValueError, AttributeError, KeyError, TypeError) as exc:
                log.warning("%s unreadable (%s); recomputing", path, exc)
        return None

    def run(self, tasks: list) -> list:
        """The predictions of :class:`fusion.experiments.parallel.FitTask` ``tasks``, in their order, trained side
        by side on the run's workers; the first failure is raised once all have run."""
        from fusion.experiments.parallel import raise_failures, run_tasks

        return raise_failures(run_tasks(tasks, self.workers, self.progress))

    def run_jobs(self, jobs: list, desc: str = "fit", unit: str = "model") -> list:
        """What the jobs of :func:`fusion.experiments.parallel.run_jobs` (e.g. calibrations) return, in their
        order, run side by side on the run's workers (``desc`` and ``unit`` label the progress bar); the first failure
        is raised once all have run."""
        from fusion.experiments.parallel import raise_failures, run_jobs

        return raise_failures(run_jobs(jobs, self.workers, self.progress, desc=desc, unit=unit))

    def store(self, objects, *, strategies, contours: int) -> tuple:
        """(the opened dataset, its record) of ``objects`` with these settings and the run's seed, generated,
        resumed or repaired by :func:`fusion.experiments.data.ensure_store` the first time a run asks for it."""
        from fusion.experiments.data import ensure_store, store_record

        key = digest(store_record(objects, contours, self.seed, strategies))
        if key not in self.stores:
            self.stores[key] = ensure_store(objects, self.path("stores"), strategies=strategies, contours=contours,
                                            seed=self.seed, workers=self.workers, progress=self.progress)
        return self.stores[key]


def _part_key(record: dict) -> str:
    """The cache key of a part: its record and the generation code of the stores it read (looked up per call)."""
    from tactile.dataset import generation_code_version

    return digest(record, generation_code_version())


__all__ = ["Context"]
