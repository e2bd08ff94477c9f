"""Objects arriving from files: :func:`load_object` (a mesh file or an Open3D mesh -> a validated, repaired
:class:`~perception.geometry.ObjectModel` in the pose-free frame) and :func:`list_collection` (a class-per-folder
mesh collection).

The door through which an object enters the house from a file; every later stage works on the
:class:`~perception.geometry.ObjectModel` (:mod:`perception.geometry`). ``perception.geometry.load_object`` and
``perception.geometry.list_collection`` still name these functions.
"""

from __future__ import annotations

import os
import reprlib
from numbers import Real
from pathlib import Path

import numpy as np
import open3d as o3d

from perception import meshio
from perception.errors import DatasetError, InvalidArgumentError, InvalidMeshError
from perception.geometry import (
    DEFAULT_SIZE_MM,
    MAX_COORDINATE_MM,
    ObjectModel,
    _check_rotation,
    check_centering,
    normalize,
    text_name,
)
from perception.orientation import orient_outward


def load_object(
    source: str | Path | o3d.geometry.TriangleMesh,
    *,
    label: str | None = None,
    size_mm: float | None = DEFAULT_SIZE_MM,
    repair: bool = True,
    name: str | None = None,
    orient: bool = True,
    centering: str = "surface",
    rotation: np.ndarray | None = None,
) -> ObjectModel:
    """Load a mesh file (OFF, OBJ, PLY, STL) or an Open3D mesh as a validated, repaired, scaled object.

    Polygon faces are fan-triangulated; texture colours (OBJ + MTL) become vertex colours. Repair
    (numpy, the same as pymeshlab's clean-up filters) merges duplicate vertices and removes duplicate and zero-area faces and unreferenced
    vertices; indices stay consistent because the arrays are rebuilt together.

    Args:
        source: a path or an ``open3d.geometry.TriangleMesh``.
        label: the class name to attach.
        size_mm: size after scaling, mm (:attr:`~perception.geometry.ObjectModel.size`: the enclosing-sphere diameter about the
            surface centroid); ``None`` keeps the source scale and position (physical sizes, e.g. captures).
        repair: run the clean-up (on by default).
        name: defaults to the file stem.
        orient: re-wind triangles consistently and outward (:func:`perception.orientation.orient_outward`:
            signed volume for closed parts, what outside rays see for open ones); on by default.
        centering: ``"surface"`` (pose-free, default) or ``"bbox"`` (the paper's bounding-box frame), see
            :func:`~perception.geometry.normalize`.
        rotation: an optional (3, 3) rotation applied to the source coordinates before anything else, to
            present the object in another pose (e.g. :func:`~perception.geometry.random_rotation`); recorded in ``transform``.

    Raises:
        MeshLoadError: missing, unreadable, unknown type, or unparseable file.
        InvalidMeshError: empty, non-finite, out-of-range indices, or nothing left after repair.
        InvalidArgumentError: a ``source`` that is neither a path (``str`` or ``pathlib.Path``; decode a ``bytes``
            path with ``os.fsdecode``) nor an Open3D ``TriangleMesh`` (arrays: build an ``ObjectModel``), a
            ``name`` or ``label`` that is not text, a ``size_mm`` that is not a positive finite number of
            millimetres up to ``MAX_COORDINATE_MM`` (or None), an unknown ``centering``, or a ``rotation`` that
            is not a finite 3 x 3 proper rotation matrix. All are checked before the file is read.

    Examples:
        >>> import pathlib, tempfile
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "cube.off"
        >>> _ = path.write_text("OFF\\n8 6 0\\n0 0 0\\n1 0 0\\n1 1 0\\n0 1 0\\n0 0 1\\n1 0 1\\n1 1 1\\n0 1 1\\n"
        ...                     "4 0 3 2 1\\n4 4 5 6 7\\n4 0 1 5 4\\n4 1 2 6 5\\n4 2 3 7 6\\n4 3 0 4 7\\n")
        >>> cube = load_object(path, label="box")
        >>> cube.n_vertices, cube.n_triangles, cube.label, round(cube.size)
        (8, 12, 'box', 150)
    """
    mesh = isinstance(source, o3d.geometry.TriangleMesh)
    path = None if mesh else _source_path(source)
    for key, value in (("name", name), ("label", label)):
        if value is not None and not isinstance(value, str):
            raise InvalidArgumentError(f"load_object: {key} must be text (a str), got {type(value).__name__} "
                                       f"{reprlib.repr(value)}")
    name = name or ("open3d-mesh" if mesh else text_name(path.stem))
    where = name if mesh else str(path)  # errors name the file when there is one
    # The arguments are checked before the file is read: a typo costs nothing.
    check_centering(centering, where)
    _check_size(size_mm, where)
    matrix = None if rotation is None else _rotation_matrix(rotation, where)
    if mesh:
        vertices = np.asarray(source.vertices, dtype=np.float64)
        triangles = np.asarray(source.triangles, dtype=np.int64)
        colors = np.asarray(source.vertex_colors, dtype=np.float64) if source.has_vertex_colors() else None
        src = None
    else:
        raw = meshio.read_mesh(path)
        vertices, triangles, colors = raw.vertices, raw.triangles, raw.vertex_colors
        src = str(path)
    vertices, triangles = meshio.validate_arrays(vertices, triangles, where)
    if repair:
        vertices, triangles, colors = meshio.repair(vertices, triangles, colors, where)
    transform = np.eye(4)
    if matrix is not None:
        transform[:3, :3] = matrix
        vertices = vertices @ transform[:3, :3].T
        if not np.isfinite(vertices).all():
            raise InvalidMeshError(f"{where}: coordinates overflow when rotated; load it with size_mm first")
    if size_mm is not None:
        try:
            vertices, scaling = normalize(vertices, size_mm, triangles=triangles, centering=centering)
        except InvalidMeshError as exc:
            raise InvalidMeshError(f"{where}: {exc}") from None
        transform = scaling @ transform
    if orient:
        triangles, _ = orient_outward(vertices, triangles, where)
    return ObjectModel(
        vertices, triangles, name=name, label=label, vertex_colors=colors, transform=transform, source=src,
        centering=centering,
    )


def _source_path(source) -> Path:
    """``source`` as a Path if it is a text path (``str`` or ``os.PathLike`` giving ``str``).

    Raises:
        InvalidArgumentError: anything else, naming its type and value and what to pass instead.
    """
    if isinstance(source, (str, os.PathLike)):
        try:
            text = os.fspath(source)
        except TypeError:
            text = None
        if isinstance(text, str):
            return Path(text)
    if isinstance(source, (bytes, os.PathLike)):
        raise InvalidArgumentError(f"load_object: a path must be text (str or pathlib.Path), got "
                                   f"{type(source).__name__} {reprlib.repr(source)}; decode it with os.fsdecode(...)")
    if isinstance(source, np.ndarray):
        raise InvalidArgumentError(
            f"load_object: expected a mesh file path or an open3d.geometry.TriangleMesh, got a numpy array of shape "
            f"{source.shape}; for vertex and triangle arrays build perception.ObjectModel(vertices, triangles)"
        )
    raise InvalidArgumentError(
        f"load_object: expected a mesh file path (str or pathlib.Path) or an open3d.geometry.TriangleMesh, got "
        f"{type(source).__name__} {reprlib.repr(source)}"
    )


def _check_size(size_mm, where: str) -> None:
    """Refuse a ``size_mm`` that is not None or a positive finite number up to ``MAX_COORDINATE_MM``."""
    if size_mm is None:
        return
    ok = isinstance(size_mm, Real) and not isinstance(size_mm, bool)
    try:
        ok = ok and bool(np.isfinite(float(size_mm))) and 0 < size_mm <= MAX_COORDINATE_MM
    except (OverflowError, TypeError, ValueError):
        ok = False
    if not ok:
        raise InvalidArgumentError(
            f"{where}: size_mm must be a positive finite number of millimetres up to {MAX_COORDINATE_MM:g}, or None "
            f"to keep the source scale; got {reprlib.repr(size_mm)}"
        )


def _rotation_matrix(rotation, where: str) -> np.ndarray:
    """``rotation`` as a float64 proper rotation matrix.

    Raises:
        InvalidArgumentError: not numbers, not 3 x 3, not finite, or not a proper rotation (each named).
    """
    try:
        r = np.asarray(rotation)
        numeric = r.dtype.kind in "iuf"
    except (TypeError, ValueError):
        numeric = False
    if not numeric:
        raise InvalidArgumentError(
            f"{where}: rotation must be a 3 x 3 matrix of numbers, got {type(rotation).__name__} "
            f"{reprlib.repr(rotation)}"
        )
    if r.shape != (3, 3):
        raise InvalidArgumentError(f"{where}: rotation must be a 3 x 3 matrix, got shape {r.shape}")
    r = r.astype(np.float64)
    if not np.isfinite(r).all():
        raise InvalidArgumentError(f"{where}: rotation is not finite (it holds NaN or Inf): {r.tolist()}")
    return _check_rotation(r, where)


def mesh_files(folder: Path) -> list[Path]:
    """The mesh files (:data:`~perception.meshio.MESH_SUFFIXES`) directly in ``folder``, sorted; hidden ones ignored."""
    return sorted(p for p in Path(folder).iterdir()
                  if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in meshio.MESH_SUFFIXES)


def list_collection(folder: str | Path) -> list[tuple[Path, str]]:
    """List a class-per-subfolder mesh collection ``<root>/<Class>/<instance>.<ext>`` (what a tactile dataset
    store is generated from; "dataset" names the store only).

    Returns (path, class name) pairs sorted by class then file name. Hidden entries are ignored.

    Raises:
        DatasetError: the folder is missing, has no class subfolders, a class folder holds no mesh files,
            or mesh files lie loose in the root.
    """
    root = Path(folder)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder (expected <root>/<Class>/<instance>.<ext>)")
    loose = sorted(p.name for p in root.iterdir() if p.is_file() and p.suffix.lower() in meshio.MESH_SUFFIXES)
    if loose:
        raise DatasetError(
            f"{root}: mesh files lie directly in the root ({', '.join(loose[:3])}...); "
            "put each in a subfolder named after its class"
        )
    classes = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not classes:
        raise DatasetError(f"{root}: no class subfolders (expected <root>/<Class>/<instance>.<ext>)")
    items: list[tuple[Path, str]] = []
    for class_dir in classes:
        files = mesh_files(class_dir)
        if not files:
            raise DatasetError(
                f"{class_dir}: class folder {class_dir.name!r} holds no mesh files "
                f"({', '.join(sorted(meshio.MESH_SUFFIXES))})"
            )
        items.extend((p, text_name(class_dir.name)) for p in files)
    return items


#: The former name of :func:`list_collection`, kept for existing scripts.
load_dataset = list_collection


__all__ = ["list_collection", "load_dataset", "load_object", "mesh_files"]
