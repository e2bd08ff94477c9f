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
        workers: store generation workers (None: the usable cores).
        timings: wall seconds of each part in this process (not cached: they say how long *this* run took).
    """

    out: Path
    seed: int
    sizes: Sizes
    classifiers: dict[str, Factory]
    progress: bool = True
    workers: int | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def path(self, *parts: str) -> Path:
        return self.out.joinpath(*parts)

    def cached_part(self, name: str, record: dict, compute: Callable[[], dict]) -> dict:
        """The JSON result of part ``name``: from ``parts/<name>.json`` when made with the same ``record``
        (measured timings are kept, so a re-run reports the same numbers), else ``compute()`` saved there."""
        path = self.path("parts", f"{name}.json")
        key = digest(record)
        if path.is_file():
            try:
                saved = json.loads(path.read_text())
                if saved.get("key") == key:
                    return saved["result"]
            except (OSError, ValueError) as exc:
                log.warning("%s unreadable (%s); recomputing", path, exc)
        result = compute()
        write_text(path, json.dumps({"key": key, "record": record, "result": result}, indent=2, default=str))
        return result


__all__ = ["Context"]
