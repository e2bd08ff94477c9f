"""The model file format: arrays in a safetensors file, everything else as JSON in its header; no code runs on load.

A model file (suffix ``.vtm``, "visuotactile model") is one `safetensors <https://huggingface.co/docs/safetensors>`_
file:

- its tensors are the model's numeric arrays (CNN weights and batch-norm statistics, the fitted arrays of the
  scikit-learn steps, input statistics), each stored with its dtype and shape;
- its header's ``__metadata__`` holds one entry, ``{"visuotactile-model": "<sha256> <JSON>"}`` (one key: the
  safetensors writer orders several keys at random, and a model should save to the same bytes every time): the
  hex SHA-256 of the JSON text and of every tensor's name, dtype, shape and bytes (a damaged file is refused,
  never read as other weights), a space, and the JSON document
  (:func:`read_model_file` returns it as ``description``) names the classifier class, its classes, sensor
  specification, probe count, taxel grid, kinesthetic cue, library versions, what it was trained on
  (``training``), its constructor parameters and its fitted state.

Fitted state is plain data, encoded by :func:`encode` as JSON with one-key tags where JSON alone is ambiguous
(``{"tuple": [...]}``, ``{"dict": {...}}``, ``{"float": "nan"}``, ``{"scalar": {"dtype", "value"}}``,
``{"strings": {...}}``, ``{"array": {"key", "order"}}`` for a tensor of the file). :func:`decode` turns it
back into numbers, strings, lists, tuples, dicts and numpy arrays, never into objects: which class the model
is rebuilt as is chosen from the classes defined in the running process (:mod:`fusion.base`), and the
classifier rebuilds its estimators from their parameters and these arrays.

Loading is bounded: the file size is checked against :data:`MAX_MODEL_BYTES` before reading, the safetensors
reader checks every tensor's dtype, shape and offsets against the file size before allocating, and JSON
nesting is limited. Damaged, truncated or hostile files raise :class:`ModelFileError` naming the file.

Version 1 of the format was a pickle; pickles are refused (:func:`looks_like_pickle`) unless the caller
opts in for a file it made itself (``load_model(path, trust_pickle=True)``).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np

from perception.atomic import atomic_path
from perception.errors import InvalidArgumentError, ModelFileError

#: Marks a safetensors file as a visuotactile model: the key of its one ``__metadata__`` entry.
FORMAT_NAME = "visuotactile-model"
#: Version of the description; 1 was the pickle format.
FORMAT_VERSION = 2
#: The suffix of model files.
SUFFIX = ".vtm"
#: Largest model file read (bytes): a paper-scale CNN pair is under 2 MB, a kNN keeps its training features.
MAX_MODEL_BYTES = 1 << 30
#: Deepest JSON nesting accepted in a description.
MAX_DEPTH = 32
#: dtype kinds stored as tensors: bool, signed and unsigned integers, floats.
ARRAY_KINDS = "biuf"

_TAGS = ("tuple", "dict", "float", "scalar", "strings", "array")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]*$")


# ----------------------------------------------------------------------------------------- encoding
def encode(value, key: str, arrays: dict[str, np.ndarray]):
    """``value`` as JSON data; numeric numpy arrays go to ``arrays`` under names starting with ``key``.

    Raises:
        TypeError: a value that is not plain data (an object, a function, an object array of non-strings).
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)) and not isinstance(value, np.generic):
        return int(value)
    if isinstance(value, float) and not isinstance(value, np.generic):
        return value if math.isfinite(value) else {"float": repr(value)}
    if isinstance(value, np.generic):
        if value.dtype.kind not in ARRAY_KINDS:
            raise TypeError(f"{key}: numpy scalar of dtype {value.dtype} cannot be stored")
        return {"scalar": {"dtype": value.dtype.str, "value": encode(value.item(), key, arrays)}}
    if isinstance(value, np.ndarray):
        if value.dtype.kind in ARRAY_KINDS:
            name = key
            while name in arrays:  # keys are paths, unique in practice; never overwrite
                name += "_"
            order = "F" if value.flags.f_contiguous and not value.flags.c_contiguous else "C"
            arrays[name] = np.array(value, order="C", copy=True)  # (ascontiguousarray makes 0-d arrays 1-d)
            return {"array": {"key": name, "order": order}}
        if value.dtype.kind in "OU" and all(isinstance(v, str) for v in value.ravel().tolist()):
            return {"strings": {"kind": value.dtype.kind, "shape": list(value.shape), "values": value.ravel().tolist()}}
        raise TypeError(f"{key}: array of dtype {value.dtype} cannot be stored")
    if isinstance(value, list):
        return [encode(v, f"{key}.{i}", arrays) for i, v in enumerate(value)]
    if isinstance(value, tuple):
        return {"tuple": [encode(v, f"{key}.{i}", arrays) for i, v in enumerate(value)]}
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"{key}: dict keys must be strings")
        return {"dict": {k: encode(v, f"{key}.{k}", arrays) for k, v in value.items()}}
    raise TypeError(f"{key}: a {type(value).__name__} cannot be stored in a model file")


def decode(value, arrays: dict[str, np.ndarray], where: str, depth: int = 0):
    """The data :func:`encode` wrote. ``where`` names the file in errors.

    Raises:
        ModelFileError: an unknown tag, a missing or mistyped array, too deep nesting.
    """
    if depth > MAX_DEPTH:
        raise ModelFileError(f"{where}: the model description is nested deeper than {MAX_DEPTH} levels")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, list):
        return [decode(v, arrays, where, depth + 1) for v in value]
    if not isinstance(value, dict) or len(value) != 1 or next(iter(value)) not in _TAGS:
        raise ModelFileError(f"{where}: unknown entry in the model description: {str(value)[:80]}")
    tag, body = next(iter(value.items()))
    if tag == "tuple":
        return tuple(decode(v, arrays, where, depth + 1) for v in _typed(body, list, where, tag))
    if tag == "dict":
        return {k: decode(v, arrays, where, depth + 1) for k, v in _typed(body, dict, where, tag).items()}
    if tag == "float":
        if body not in ("nan", "inf", "-inf"):
            raise ModelFileError(f"{where}: bad float {body!r} in the model description")
        return float(body)
    if tag == "scalar":
        body = _typed(body, dict, where, tag)
        dtype = _dtype(body.get("dtype"), where)
        item = decode(body.get("value"), arrays, where, depth + 1)
        if not isinstance(item, (bool, int, float)):
            raise ModelFileError(f"{where}: bad numpy scalar {str(body)[:80]} in the model description")
        try:
            return dtype.type(item)
        except (OverflowError, ValueError, TypeError) as exc:
            raise ModelFileError(f"{where}: bad numpy scalar {str(body)[:80]} ({exc})") from None
    if tag == "strings":
        body = _typed(body, dict, where, tag)
        values, shape, kind = body.get("values"), body.get("shape"), body.get("kind")
        if (kind not in ("O", "U") or not isinstance(values, list) or not all(isinstance(v, str) for v in values)
                or not _shape_ok(shape) or math.prod(shape) != len(values)):
            raise ModelFileError(f"{where}: bad string array in the model description")
        return np.array(values, dtype=object if kind == "O" else str).reshape(shape)
    body = _typed(body, dict, where, tag)  # "array"
    key, order = body.get("key"), body.get("order", "C")
    if not isinstance(key, str) or key not in arrays or order not in ("C", "F"):
        raise ModelFileError(f"{where}: the model description refers to a missing array {str(key)[:80]!r}")
    array = arrays[key].copy()
    return np.asfortranarray(array) if order == "F" else array


def _typed(body, kind: type, where: str, tag: str):
    if not isinstance(body, kind):
        raise ModelFileError(f"{where}: bad {tag!r} entry in the model description")
    return body


def _shape_ok(shape) -> bool:
    return isinstance(shape, list) and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)


def _dtype(spec, where: str) -> np.dtype:
    try:
        dtype = np.dtype(spec) if isinstance(spec, str) else None
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in ARRAY_KINDS or dtype.itemsize > 8:
        raise ModelFileError(f"{where}: bad dtype {str(spec)[:40]!r} in the model description")
    return dtype


# -------------------------------------------------------------------------------------------- files
def looks_like_pickle(head: bytes) -> bool:
    """Whether ``head`` (a file's first 9 bytes) starts like a pickle of protocol 2 or later (our format 1) and not
    like a safetensors file: a header length (u64, little-endian) whose low bytes happen to be 0x80 0x02..0x05 (a
    header of 640 + 256 k bytes, say) followed by the header's ``{`` is a model file, not a pickle."""
    if len(head) >= 9 and head[8:9] == b"{" and head[4:8] == b"\0\0\0\0":
        return False
    return len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5


def write_model_file(path: str | Path, description: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``description`` (JSON data) and ``arrays`` to the model file ``path`` atomically."""
    from safetensors.numpy import save

    text = json.dumps(description, sort_keys=True, allow_nan=False, separators=(",", ":"))
    # Little-endian, as safetensors stores and the reader returns them: the digest is of what the file holds.
    arrays = {k: np.array(v, dtype=np.asarray(v).dtype.newbyteorder("<"), order="C", copy=True)
              for k, v in arrays.items()}
    data = save(arrays, metadata={FORMAT_NAME: f"{content_digest(text, arrays)} {text}"})
    if Path(path).is_dir():
        raise ModelFileError(f"{path}: is a folder; give the model file's name (e.g. {Path(path) / ('model' + SUFFIX)})")
    try:
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    except (FileExistsError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError) as exc:
        # a bad path, named; a full disk or an I/O error stays an OSError (the old file is kept either way)
        raise ModelFileError(f"{path}: cannot write the model file ({exc.strerror or exc})") from None
    return Path(path)


def read_model_file(path: str | Path, max_bytes: int = MAX_MODEL_BYTES) -> tuple[dict, dict[str, np.ndarray]]:
    """(description, arrays) of the model file ``path``; nothing in it is executed.

    Raises:
        ModelFileError: no such file, larger than ``max_bytes``, a pickle, not a visuotactile model file,
            damaged or truncated, or of a newer format version.
    """
    path = Path(path)
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, (int, np.integer)) or max_bytes < 1:
        raise InvalidArgumentError(f"max_bytes must be a positive number of bytes, got {max_bytes!r}")
    if not path.is_file():
        raise ModelFileError(f"{path}: no such model file")
    size = path.stat().st_size
    if size > max_bytes:
        raise ModelFileError(
            f"{path}: {size} bytes, more than the {max_bytes}-byte limit for model files "
            "(fusion.modelfile.MAX_MODEL_BYTES; pass max_bytes= to load_model to raise it)"
        )
    with open(path, "rb") as f:
        head = f.read(9)
    if looks_like_pickle(head):
        raise ModelFileError(
            f"{path}: a pickle (visuotactile's old model format, or anything else): unpickling can run code, so "
            "it is refused. If you made this file yourself, load it with load_model(path, trust_pickle=True) "
            "(command line: --trust-pickle) and save it again, which writes the safe format"
        )
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="numpy") as f:
            entry = (f.metadata() or {}).get(FORMAT_NAME)
            if not isinstance(entry, str):
                raise ModelFileError(f"{path}: a safetensors file, but not a visuotactile model (no {FORMAT_NAME!r})")
            digest, _, text = entry.partition(" ")
            keys = list(f.keys())
            for key in keys:  # the dtype and shape of every tensor are checked before one is read
                info = f.get_slice(key)
                if np.dtype(_numpy_dtype(info.get_dtype())).kind not in ARRAY_KINDS:
                    raise ModelFileError(f"{path}: tensor {key!r} has unsupported dtype {info.get_dtype()}")
            arrays = {key: f.get_tensor(key) for key in keys}
    except ModelFileError:
        raise
    except Exception as exc:  # noqa: BLE001 -- safetensors raises its own error type (and others) for damaged files
        raise ModelFileError(
            f"{path}: not a readable visuotactile model file ({type(exc).__name__}: {str(exc)[:200]})"
        ) from None
    if digest != content_digest(text, arrays):
        raise ModelFileError(f"{path}: damaged model file (its checksum does not match its content)")
    try:
        description = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ModelFileError(f"{path}: damaged model description ({str(exc)[:200]})") from None
    if not isinstance(description, dict):
        raise ModelFileError(f"{path}: the model description is missing or not a JSON object")
    version = description.get("version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise ModelFileError(f"{path}: the model description has no format version")
    if version > FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: model format {version} is newer than this library's {FORMAT_VERSION}; update visuotactile"
        )
    for key, array in arrays.items():
        if not _NAME.match(key):
            raise ModelFileError(f"{path}: bad tensor name {key[:80]!r}")
        array.setflags(write=False)
    return description, arrays


def content_digest(text: str, arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 (hex) of a model's JSON text and of every array's name, dtype, shape and bytes."""
    h = hashlib.sha256(text.encode("utf-8"))
    for key in sorted(arrays):
        value = arrays[key]
        h.update(f"\0{key}\0{value.dtype.str}\0{value.shape}\0".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    return h.hexdigest()


def _numpy_dtype(name: str) -> str:
    """numpy dtype of a safetensors dtype name (``F32``, ``I64``, ``BOOL``, ...); '' for the unsupported."""
    table = {"BOOL": "bool", "U8": "uint8", "I8": "int8", "U16": "uint16", "I16": "int16", "U32": "uint32",
             "I32": "int32", "U64": "uint64", "I64": "int64", "F16": "float16", "F32": "float32", "F64": "float64"}
    return table.get(name, "O")


__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "MAX_MODEL_BYTES", "SUFFIX", "content_digest", "decode", "encode",
           "looks_like_pickle", "read_model_file", "write_model_file"]
