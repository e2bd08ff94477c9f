"""What a dataset is generated from: object specifications that a worker process can load by itself."""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perception.errors import DatasetError
from perception.geometry import ObjectModel, text_name


def _stable_repr(value, where: str = "a loader argument", _open: frozenset = frozenset()) -> str:
    """``repr`` of a loader's arguments that names their content: arrays by shape, dtype and SHA-256 of their bytes
    (numpy's repr elides the middle of a large array, so two different arrays would read the same), dataclasses
    (meshes among them) field by field, tuples, lists and dicts element by element; plain values by ``repr``.

    Raises:
        DatasetError: an argument whose ``repr`` elides its content ("...": a large tensor, say), which could not
            tell two stores apart; ``where`` names the object in the message.
    """
    if value is None or isinstance(value, (str, bytes, bool, int, float, complex, np.generic)):
        return repr(value)
    if id(value) in _open:  # a container holding itself
        return "..."
    inner = _open | {id(value)}
    if isinstance(value, np.ndarray):
        head = f"{type(value).__name__}(shape={value.shape}, dtype={value.dtype}"
        if value.dtype.hasobject:
            return f"{head}, items={_stable_repr(value.ravel().tolist(), where, inner)})"
        content = hashlib.sha256(np.ascontiguousarray(value).view(np.uint8).tobytes())
        if isinstance(value, np.ma.MaskedArray):
            content.update(np.ascontiguousarray(np.ma.getmaskarray(value)).tobytes())
        return f"{head}, sha256={content.hexdigest()})"
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = ", ".join(f"{f.name}={_stable_repr(getattr(value, f.name), where, inner)}"
                           for f in dataclasses.fields(value))
        return f"{type(value).__name__}({fields})"
    if isinstance(value, (tuple, list)):
        items = [_stable_repr(v, where, inner) for v in value]
        if type(value) is list:
            return "[" + ", ".join(items) + "]"
        text = f"({', '.join(items)},)" if len(items) == 1 else f"({', '.join(items)})"
        return text if type(value) is tuple else f"{type(value).__name__}{text}"
    if isinstance(value, dict):
        text = "{" + ", ".join(f"{_stable_repr(k, where, inner)}: {_stable_repr(v, where, inner)}"
                               for k, v in value.items()) + "}"
        return text if type(value) is dict else f"{type(value).__name__}({text})"
    text = repr(value)
    if "..." in text:
        raise DatasetError(f"{where}: the loader argument {type(value).__name__} reads {text[:60]!r}..., eliding its "
                           "content; pass it as a numpy array or plain values so that the store can be told apart")
    return text


@dataclass(frozen=True)
class ObjectSpec:
    """One object to explore, small and picklable: the worker loads it, the parent never does.

    Exactly one source: ``path`` (a mesh file, loaded with :func:`perception.geometry.load_object`),
    ``catalogue`` ((class, seed) of :func:`perception.shapes.make_object`) or ``loader`` (a picklable
    zero-argument callable returning an :class:`ObjectModel`, e.g. a module-level function or a
    ``functools.partial`` of one).

    Attributes:
        name: unique within a dataset; seeds derive from it (with the dataset seed, strategy, contour).
        label: the class name.
        path: made absolute, since workers (Ray ones included) may run in another folder.
        rotation_seed: present the object in the pose :func:`perception.geometry.random_rotation` draws from
            this seed (uniform over all rotations), applied to the raw mesh before loading; None: as stored.
        made_from: the object this one is made from (e.g. a camera capture of it, :mod:`tactile.captures`), or
            None. Splits by object keep an object and what is made from it on one side
            (:meth:`~tactile.dataset.reader.TactileDataset.mesh_ids`).

    Raises:
        DatasetError: an empty name or label, not exactly one source, a rotation seed that is not a
            non-negative integer, or a ``made_from`` that is not an ObjectSpec.
    """

    name: str
    label: str
    path: str | None = None
    catalogue: tuple[str, int] | None = None
    loader: Callable[[], ObjectModel] | None = None
    rotation_seed: int | None = None
    made_from: ObjectSpec | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise DatasetError(f"object spec needs a non-empty name, got {self.name!r}")
        if not isinstance(self.label, str) or not self.label:
            raise DatasetError(f"object {self.name!r}: needs a class label (non-empty string), got {self.label!r}")
        sources = [s for s in (self.path, self.catalogue, self.loader) if s is not None]
        if len(sources) != 1:
            raise DatasetError(f"object {self.name!r}: give exactly one of path, catalogue or loader")
        if self.path is not None:
            object.__setattr__(self, "path", str(Path(self.path).resolve()))
        seed = self.rotation_seed
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise DatasetError(f"object {self.name!r}: rotation_seed must be a non-negative integer, got {seed!r}")
        if self.made_from is not None and not isinstance(self.made_from, ObjectSpec):
            raise DatasetError(f"object {self.name!r}: made_from must be an ObjectSpec or None, got "
                               f"{type(self.made_from).__name__}")

    def load(self) -> ObjectModel:
        """Load the object (in the worker), in its pose. Raises what the loader raises (MeshLoadError, ...)."""
        from perception.geometry import random_rotation, rotate

        rotation = None if self.rotation_seed is None else random_rotation(int(self.rotation_seed))
        if self.path is not None:
            from perception.geometry import load_object

            return load_object(self.path, label=self.label, name=self.name, rotation=rotation)
        if self.catalogue is not None:
            from perception.shapes import make_object

            model = make_object(self.catalogue[0], int(self.catalogue[1]))
        else:
            model = self.loader()
            if not isinstance(model, ObjectModel):
                raise DatasetError(f"object {self.name!r}: loader returned {type(model).__name__}, not ObjectModel")
        if rotation is not None:
            model = rotate(model, rotation)
        model.name, model.label = self.name, self.label
        return model

    def to_dict(self) -> dict[str, Any]:
        """JSON-able identity (stored in the dataset settings; resuming compares it). A loader's arguments are written
        by content (:func:`_stable_repr`).

        Raises:
            DatasetError: a loader argument whose ``repr`` elides its content.
        """
        out: dict[str, Any] = {"name": self.name, "label": self.label}
        if self.path is not None:
            out["path"] = str(self.path)
        elif self.catalogue is not None:
            out["catalogue"] = [self.catalogue[0], int(self.catalogue[1])]
        else:
            fn = getattr(self.loader, "func", self.loader)  # functools.partial -> its function
            out["loader"] = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
            if hasattr(self.loader, "args"):
                out["loader_args"] = _stable_repr((self.loader.args, self.loader.keywords), self.name)
        if self.rotation_seed is not None:
            out["rotation_seed"] = int(self.rotation_seed)
        if self.made_from is not None:
            out["made_from"] = self.made_from.to_dict()
        return out


def object_specs(objects) -> list[ObjectSpec]:
    """Normalise what :func:`generate` accepts into specs.

    ``objects`` is a class-per-folder mesh collection (a path, see :func:`perception.geometry.list_collection`;
    names "Class/stem"), a list of (path, label) pairs (names "label/stem"), a list of catalogue pairs
    (class, seed) with a class of :data:`perception.shapes.CLASSES` (names "class/seed"), or a list of
    :class:`ObjectSpec` (mixing is allowed).

    Raises:
        DatasetError: an empty list, an item of none of these forms, an unknown catalogue class, or two
            objects with the same name.
    """
    if isinstance(objects, (str, Path)):
        from perception.geometry import list_collection

        objects = list_collection(objects)
    from perception.shapes import CLASSES

    specs: list[ObjectSpec] = []
    for item in objects:
        if isinstance(item, ObjectSpec):
            specs.append(item)
            continue
        if not (isinstance(item, (tuple, list)) and len(item) == 2):
            raise DatasetError(f"object {item!r}: expected (path, label), (class, seed) or an ObjectSpec")
        first, second = item
        if isinstance(first, str) and first in CLASSES and isinstance(second, int) and not isinstance(second, bool):
            if second < 0:
                raise DatasetError(f"catalogue object {item!r}: the seed must be >= 0")
            specs.append(ObjectSpec(f"{first}/{second}", first, catalogue=(first, second)))
        elif isinstance(first, (str, Path)) and isinstance(second, str):
            path = Path(first)
            specs.append(ObjectSpec(f"{text_name(str(second))}/{text_name(path.stem)}", text_name(str(second)),
                                    path=str(path)))
        elif isinstance(first, str) and first in CLASSES:
            raise DatasetError(f"catalogue object {item!r}: the seed must be a non-negative integer, got {second!r}")
        elif isinstance(first, str) and isinstance(second, int):
            raise DatasetError(
                f"catalogue object {item!r}: unknown class {first!r}; the built-in classes are {', '.join(CLASSES)}"
            )
        else:
            raise DatasetError(f"object {item!r}: expected (path, label), (class, seed) or an ObjectSpec")
    if not specs:
        raise DatasetError("no objects given to generate a dataset from")
    seen: dict[str, int] = {}
    for i, spec in enumerate(specs):
        if spec.name in seen:
            raise DatasetError(
                f"objects {seen[spec.name]} and {i} are both named {spec.name!r}; names must be unique "
                "(seeds derive from them)"
            )
        seen[spec.name] = i
    return specs


__all__ = ["ObjectSpec", "object_specs"]
