"""Tactile datasets: :func:`generate` a zarr store (local processes or Ray), :func:`open_dataset` to read it.

    from tactile.dataset import generate, open_dataset

    generate([("mug", 0), ("box", 0)], "out/small.zarr", contours_per_object=50)  # or a mesh folder
    ds = open_dataset("out/small.zarr")
    train, test = ds.split_by_object(0.2, seed=0, index=ds.indices("guided"))
    batch = ds.load(train)                 # a SequenceBatch (float32 frames in memory)
    items = ds.torch_dataset(test)         # a torch Dataset reading one sequence chunk per item
    verify_store("out/small.zarr").damaged # {object: what is wrong}; generate re-explores those
    rerun_objects("out/small.zarr", 2).differ  # objects explored again whose bytes differ (forged, other code)

Sequence k of strategy s of object o is what ``explore_object(model, s, 1, sensor, probes,
seed=contour_seed(seed, o, s, k))`` gives (a guided strategy: with ``planes=[Toucher(model, s).pair_order(
pair_order_seed(seed, o, s))[k]]``, its pairs without repeats), frames within the encoding's quantisation
step / 2. See
:mod:`tactile.dataset.store` for the layout, the frame encoding and the checksums that make damage an error.
"""

from tactile.dataset.generate import EXECUTORS, GenerationReport, generate
from tactile.dataset.integrity import VerifyReport, verify_store
from tactile.dataset.objects import ObjectSpec, object_specs
from tactile.dataset.reader import TactileDataset, open_dataset
from tactile.dataset.rerun import RerunReport, rerun_objects
from tactile.dataset.store import contour_seed, frame_encoding, pair_order_seed
from tactile.dataset.version import generation_code_version

__all__ = [
    "EXECUTORS",
    "GenerationReport",
    "ObjectSpec",
    "RerunReport",
    "TactileDataset",
    "VerifyReport",
    "contour_seed",
    "frame_encoding",
    "generate",
    "generation_code_version",
    "object_specs",
    "open_dataset",
    "pair_order_seed",
    "rerun_objects",
    "verify_store",
]
