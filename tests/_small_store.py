"""The small store and kNN model file the trust-boundary tests damage: two catalogue objects, blind, 6 contours of
6 probes on an 8 x 8 pad (a second to make), and a kNN trained on all of it through the command line."""

from __future__ import annotations

from pathlib import Path

from fusion.cli import main
from tactile.dataset import generate
from tactile.sensor import FSRSensor

OBJECTS = [("box", 0), ("ring", 0)]
SETTINGS = {"strategies": ("blind",), "contours_per_object": 6, "sensor": FSRSensor(rows=8, cols=8), "probes": 6,
            "seed": 0, "workers": 1, "progress": False}


def small_store(out: Path) -> Path:
    """The small store generated at ``out``."""
    generate(OBJECTS, out, **SETTINGS)
    return out


def small_knn_model(store: Path, path: Path) -> Path:
    """A kNN trained on all of ``store`` by ``visuotactile train``, saved at ``path``."""
    assert main(["train", "--store", str(store), "--model", "knn", "--out", str(path), "--split", "none",
                 "--no-progress"]) == 0
    return path
