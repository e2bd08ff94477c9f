"""Touching: contours on the object surface, the virtual FSR tactile array pressed along them, datasets.

Names are imported on first use (PEP 562): ``import tactile`` alone loads nothing heavy.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Contour": "contours",
    "Plane": "contours",
    "make_contour": "contours",
    "plane_through": "contours",
    "section": "contours",
    "SequenceBatch": "explore",
    "TactileSequence": "explore",
    "explore": "explore",
    "FSRSensor": "sensor",
    "explore_object": "sampling",
    "sample_planes": "sampling",
    "TactileDataset": "dataset",
    "generate": "dataset",
    "open_dataset": "dataset",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'tactile' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"tactile.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
