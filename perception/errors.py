"""The exception hierarchy shared by every visuotactile package.

Every error a user can trigger with bad input is a subclass of :class:`VisuotactileError`, and its message
names the file or object concerned and the problem, so that ``except VisuotactileError`` catches all of
them and the text alone says what to fix.
"""

from __future__ import annotations


class VisuotactileError(Exception):
    """Base class of all visuotactile errors."""


class InvalidArgumentError(VisuotactileError, ValueError):
    """An argument names an unknown method or channel, or is of the wrong type or out of range (a seed, a
    count, an image size). Also a ``ValueError``, which these cases raised before. Every argument check
    raises it (or a subclass), whichever package it is in."""


class MeshLoadError(VisuotactileError):
    """A mesh file is missing, unreadable, of an unknown type, or cannot be parsed."""


class InvalidMeshError(VisuotactileError):
    """Mesh arrays are empty, non-finite, badly shaped or index out of range, or nothing is left after repair."""


class ContourError(VisuotactileError):
    """A cutting plane is degenerate (near-collinear points) or misses the object, or a contour is unusable."""


class SensorSpecError(InvalidArgumentError):
    """A tactile sensor specification or a probe list is invalid (zero/negative sizes, empty list, ...): an
    argument check of the sensor's declared parameters."""


class SaliencyError(VisuotactileError):
    """A saliency/attention request is invalid (unknown method, bad weights, bad ground-truth file)."""


class DatasetError(VisuotactileError):
    """A dataset folder or store is empty, malformed, or does not match what was asked for."""


class DataLeakError(DatasetError):
    """Train and test share sequences, objects or meshes where the evaluation claims held-out or unseen data."""


class ModelMismatchError(VisuotactileError):
    """A trained model is given data from another sensor spec or class list."""


class ModelFileError(ModelMismatchError):
    """A model file is missing, truncated, damaged or hostile, not a visuotactile model, of a newer format, or a
    pickle (refused: unpickling can run code)."""


class NotFittedError(VisuotactileError, ValueError, AttributeError):
    """A classifier is used (predict, save, compare) before it was fitted. Also a ``ValueError`` and an
    ``AttributeError``, as scikit-learn's ``NotFittedError`` that it replaces."""


class WorkerError(VisuotactileError, RuntimeError):
    """A worker process died (crashed, killed or out of memory) before it finished its task; the caller lives on."""


class DeviceNotFoundError(VisuotactileError):
    """No depth camera is connected (or it cannot be opened)."""


def shown(value) -> str:
    """``value`` as an error message shows it: :func:`reprlib.repr` (long values abbreviated), and an integer too long
    for Python to print (over 4,300 digits raise ValueError in ``repr``) by its size instead."""
    import reprlib

    try:
        return reprlib.repr(value)
    except ValueError:
        return f"an integer of {value.bit_length():,} bits" if isinstance(value, int) else f"a {type(value).__name__}"


__all__ = [
    "ContourError",
    "DataLeakError",
    "DatasetError",
    "DeviceNotFoundError",
    "InvalidArgumentError",
    "InvalidMeshError",
    "MeshLoadError",
    "ModelFileError",
    "ModelMismatchError",
    "NotFittedError",
    "SaliencyError",
    "SensorSpecError",
    "VisuotactileError",
    "WorkerError",
    "shown",
]
