"""Tactile datasets: :func:`generate` a zarr store (local processes or Ray), :func:`open_dataset` to read it.

See :mod:`tactile.dataset.store` for the layout and the frame encoding.
"""

from tactile.dataset.generate import EXECUTORS, GenerationReport, generate
from tactile.dataset.objects import ObjectSpec, object_specs
from tactile.dataset.reader import TactileDataset, open_dataset
from tactile.dataset.store import contour_seed, frame_encoding

__all__ = [
    "EXECUTORS",
    "GenerationReport",
    "ObjectSpec",
    "TactileDataset",
    "contour_seed",
    "frame_encoding",
    "generate",
    "object_specs",
    "open_dataset",
]
