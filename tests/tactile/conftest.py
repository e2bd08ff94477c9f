"""Fixtures of the store tests: ``store``, the small store of :mod:`tests._small_store` (made once per module), and
``copy``, a fresh copy of it to damage. A module testing another store defines its own ``store`` and ``copy``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests._small_store import small_store


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return small_store(tmp_path_factory.mktemp("small-store") / "small.zarr")


@pytest.fixture
def copy(store, tmp_path) -> Path:
    return Path(shutil.copytree(store, tmp_path / "copy.zarr"))
