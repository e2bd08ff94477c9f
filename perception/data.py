"""Where the shared real data sets are: ``$VISUOTACTILE_DATA``, else ``../shared/data`` beside the checkout.

The core library and its tests never need them (the catalogue, analytic shapes and files the tests write
suffice); the real-data tests, ``reproduce --data`` examples and the benchmarks read them in place from here.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Environment variable naming the shared data folder.
DATA_ENV = "VISUOTACTILE_DATA"


def data_folder() -> Path:
    """The shared data folder: ``$VISUOTACTILE_DATA`` when set, else ``shared/data`` next to the repository
    folder (``../shared/data`` seen from the checkout). It may not exist; callers check and say so."""
    if os.environ.get(DATA_ENV):
        return Path(os.environ[DATA_ENV])
    return Path(__file__).resolve().parents[2] / "shared" / "data"


#: :func:`data_folder` when this module was imported.
DATA = data_folder()

__all__ = ["DATA", "DATA_ENV", "data_folder"]
