"""Objects arriving from files: :func:`load_object` (a mesh file or an Open3D mesh -> a validated, repaired
:class:`~perception.geometry.ObjectModel` in the pose-free frame) and :func:`list_collection` (a class-per-folder
mesh collection).

The door through which an object enters the house from a file; every later stage works on the
:class:`~perception.geometry.ObjectModel` (:mod:`perception.geometry`). ``perception.geometry.load_object`` and
``perception.geometry.list_collection`` still name these functions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from perception import meshio
from perception.errors import DatasetError, InvalidMeshError
from perception.geometry import (
    DEFAULT_SIZE_MM,
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
        InvalidArgumentError: an unknown ``centering`` or a ``rotation`` that is not a proper rotation matrix.

    Examples:
        >>> import pathlib, tempfile
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "cube.off"
        >>> _ = path.write_text("OFF\\n8 6 0\\n0 0 0\\n1 0 0\\n1 1 0\\n0 1 0\\n0 0 1\\n1 0 1\\n1 1 1\\n0 1 1\\n"
        ...                     "4 0 3 2 1\\n4 4 5 6 7\\n4 0 1 5 4\\n4 1 2 6 5\\n4 2 3 7 6\\n4 3 0 4 7\\n")
        >>> cube = load_object(path, label="box")
        >>> cube.n_vertices, cube.n_triangles, cube.label, round(cube.size)
        (8, 12, 'box', 150)
    """
    check_centering(centering, str(name or source))
    if isinstance(source, o3d.geometry.TriangleMesh):
        name = name or "open3d-mesh"
        vertices = np.asarray(source.vertices, dtype=np.float64)
        triangles = np.asarray(source.triangles, dtype=np.int64)
        colors = np.asarray(source.vertex_colors, dtype=np.float64) if source.has_vertex_colors() else None
        src = None
    else:
        path = Path(source)
        name = name or text_name(path.stem)
        raw = meshio.read_mesh(path)
        vertices, triangles, colors = raw.vertices, raw.triangles, raw.vertex_colors
        src = str(path)
    where = src or name  # errors name the file when there is one
    vertices, triangles = meshio.validate_arrays(vertices, triangles, where)
    if repair:
        vertices, triangles, colors = meshio.repair(vertices, triangles, colors, where)
    transform = np.eye(4)
    if rotation is not None:
        transform[:3, :3] = _check_rotation(rotation, where)
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
        files = sorted(
            p
            for p in class_dir.iterdir()
            if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in meshio.MESH_SUFFIXES
        )
        if not files:
            raise DatasetError(
                f"{class_dir}: class folder {class_dir.name!r} holds no mesh files "
                f"({', '.join(sorted(meshio.MESH_SUFFIXES))})"
            )
        items.extend((p, text_name(class_dir.name)) for p in files)
    return items


#: The former name of :func:`list_collection`, kept for existing scripts.
load_dataset = list_collection


__all__ = ["list_collection", "load_dataset", "load_object"]
