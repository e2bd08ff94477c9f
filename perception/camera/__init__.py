"""RGB-D capture: the :class:`RGBDFrame` and the sources that yield it (OAK live, recordings, a virtual OAK).

Names are imported on first use (PEP 562), so ``from perception.camera import find_oak_devices`` does not
load Open3D, and depthai is imported only inside :mod:`perception.camera.oak` when a camera is used.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Intrinsics": "frame",
    "RGBDFrame": "frame",
    "OakCamera": "oak",
    "find_oak_devices": "oak",
    "NO_DEVICE_HINT": "oak",
    "is_recording": "recording",
    "read_recording": "recording",
    "write_recording": "recording",
    "OAK_BASELINE_MM": "virtual",
    "OAK_MODES": "virtual",
    "StereoNoise": "virtual",
    "VirtualOakCamera": "virtual",
    "look_at": "virtual",
}

__all__ = [
    "NO_DEVICE_HINT",
    "OAK_BASELINE_MM",
    "OAK_MODES",
    "Intrinsics",
    "OakCamera",
    "RGBDFrame",
    "StereoNoise",
    "VirtualOakCamera",
    "find_oak_devices",
    "is_recording",
    "look_at",
    "read_recording",
    "write_recording",
]


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"perception.camera.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'perception.camera' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
