"""Train/test leakage checks from what a model actually trained on.

A fitted classifier keeps a fingerprint of every sequence it was fitted on (``model.training_["fingerprints"]``:
one 64-bit BLAKE2b hash per sequence of its frames and per-probe arrays, set by
:meth:`fusion.base.TactileClassifier.fit` and saved in the model file). Whatever code chose the training rows, an
evaluation that claims held-out sequences can then be checked against the data itself: :func:`check_held_out`
refuses test sequences the model was fitted on, and (for unseen-object claims) test objects any of whose sequences
it was fitted on. Identical sequences (the same bytes) count as one, so a copied store or a duplicated object
cannot hide a leak.
"""

from __future__ import annotations

import hashlib
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from perception.errors import DataLeakError
from perception.limits import limit
from perception.runtime import usable_cores

#: The key of the fingerprints in ``model.training_``.
KEY = "fingerprints"


#: Fields of a training record (:class:`fusion.training.TrainingRecord` plus the fingerprints) and their types.
RECORD_FIELDS = {"store": (str,), "store_id": (str,), "split": (str,), "strategy": (str, type(None)),
                 "test_fraction": (int, float), "seed": (int,), "train_sequences": (int,)}
#: How a training record may split a store (:data:`fusion.training.SPLITS`).
SPLITS = ("sequence", "object", "none")


def check_training_record(training, where: str) -> dict | None:
    """A model file's training record, checked field by field (types, the fingerprints a 1-D integer array).

    Raises:
        ModelFileError: naming ``where`` and the field.
    """
    from perception.errors import ModelFileError

    if training is None:
        return None
    if not isinstance(training, dict):
        raise ModelFileError(f"{where}: the model's training record is not a mapping")
    for key, kinds in RECORD_FIELDS.items():
        if key in training and (not isinstance(training[key], kinds) or isinstance(training[key], bool)):
            raise ModelFileError(f"{where}: the model's training record has a bad {key!r}: {training[key]!r}"[:300])
    # values too: `evaluate` re-splits the store by them, and a bad one would read as a bad command-line option
    from tactile.sampling import STRATEGIES

    valid = {"split": lambda v: v in SPLITS, "strategy": lambda v: v is None or v in STRATEGIES,
             "test_fraction": lambda v: 0 < v < 1, "seed": lambda v: 0 <= v < 2**63,
             "train_sequences": lambda v: 0 <= v <= limit("sequences")}
    for key, ok in valid.items():
        if key in training and not ok(training[key]):
            raise ModelFileError(f"{where}: the model's training record has an impossible {key!r}: "
                                 f"{training[key]!r}"[:300])
    prints = training.get(KEY)
    if prints is not None and not (isinstance(prints, np.ndarray) and prints.ndim == 1
                                   and prints.dtype.kind in "iu"):
        raise ModelFileError(f"{where}: the model's training fingerprints are not a 1-D integer array")
    return training


def sequence_fingerprints(batch) -> np.ndarray:
    """(S,) int64: a 64-bit BLAKE2b hash of each sequence's frames, normals, positions and pad sides (its bytes as
    float32, so a stored and a freshly loaded copy agree)."""
    parts = [np.ascontiguousarray(np.asarray(getattr(batch, name), dtype=np.float32)).reshape(len(batch), -1)
             for name in ("frames", "normals", "positions", "pad_sides_mm") if getattr(batch, name, None) is not None]
    out = np.empty(len(batch), dtype=np.int64)

    def hash_rows(rows: range) -> None:
        for i in rows:
            h = hashlib.blake2b(digest_size=8)
            for part in parts:
                h.update(part[i])  # the row's buffer: no copy
            out[i] = np.frombuffer(h.digest(), dtype=np.int64)[0]

    # hashlib releases the GIL over large buffers: the rows are hashed on one thread per core (18,240 SHREC
    # sequences on 2 cores: 2.2 -> 1.0 s).
    workers = min(usable_cores(), max(len(batch) // 256, 1))
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(hash_rows, [range(k, len(batch), workers) for k in range(workers)]))
    return out


def fingerprints_of(model) -> np.ndarray | None:
    """The fingerprints of the sequences ``model`` was fitted on (None for a model saved without them)."""
    info = getattr(model, "training_", None)
    if not isinstance(info, dict) or info.get(KEY) is None:
        return None
    return np.asarray(info[KEY], dtype=np.int64).reshape(-1)


def overlap(model, batch) -> np.ndarray:
    """Boolean (S,): which sequences of ``batch`` the model was fitted on (all False without fingerprints)."""
    trained = fingerprints_of(model)
    if trained is None:
        return np.zeros(len(batch), dtype=bool)
    return np.isin(sequence_fingerprints(batch), trained)


def check_held_out(model, batch, what: str, *, by_object: bool = False) -> None:
    """Refuse to score ``batch`` as held-out data when the model was fitted on any of its sequences, or, with
    ``by_object``, on any sequence of one of its objects (``batch.object_ids``).

    Raises:
        DataLeakError: naming ``what``, how many sequences / which objects leak.
    """
    seen = overlap(model, batch)
    if not seen.any():
        return
    if by_object:
        names = np.asarray(batch.object_names, dtype=object)[np.unique(batch.object_ids[seen])]
        raise DataLeakError(f"{what}: the model was fitted on sequences of {len(names)} test object(s) "
                            f"({', '.join(map(str, names[:5]))}): these are not unseen objects")
    raise DataLeakError(f"{what}: the model was fitted on {int(seen.sum())} of the {len(batch)} test sequences: "
                        "they are not held out")


__all__ = ["KEY", "RECORD_FIELDS", "DataLeakError", "check_held_out", "check_training_record", "fingerprints_of", "overlap",
           "sequence_fingerprints"]
