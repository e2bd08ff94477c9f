"""Objects, geometry and visual attention: the bottom of the visuotactile stack.

Names are imported on first use (PEP 562), so ``import perception.errors`` (as the command line does
before it knows what it will run) does not load Open3D.
"""

from __future__ import annotations

import importlib

from perception.runtime import package_version

#: The toolkit's version (installed metadata, else the checkout's setup.cfg); models and stores record it.
__version__ = package_version()

_EXPORTS = {
    "VisuotactileError": "errors",
    "Curvature": "geometry",
    "ObjectModel": "geometry",
    "list_collection": "loading",
    "load_dataset": "loading",
    "load_object": "loading",
    "CLASSES": "shapes",
    "make_object": "shapes",
    "load_points": "reconstruct.surface",
}

__all__ = ["CLASSES", "Curvature", "ObjectModel", "VisuotactileError", "__version__", "list_collection", "load_dataset", "load_object", "load_points", "make_object"]


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'perception' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"perception.{_EXPORTS[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
