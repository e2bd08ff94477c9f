"""Object geometry: the :class:`ObjectModel` every stage works on, and the loaders that build it.

Units are millimetres. A loaded object is centred on its bounding-box centre and scaled to a bounding-box
diagonal of ``size_mm`` (150 mm by default, a hand-held object); ``ObjectModel.transform`` maps the
source file's coordinates to the model's. Expensive derived data (normals, curvature, the ray-casting
scene) are computed on first use and cached, so a scene pays only for what it asks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import open3d as o3d

from perception import meshio
from perception.curvature import Curvature, compute_curvature, vertex_normals
from perception.errors import DatasetError, InvalidMeshError

log = logging.getLogger(__name__)

#: Default bounding-box diagonal of a loaded object, in millimetres.
DEFAULT_SIZE_MM = 150.0

@dataclass(eq=False)
class ObjectModel:
    """A triangle mesh in millimetres with lazily cached normals, curvature and ray-casting scene.

    Attributes:
        vertices: (V, 3) float64 positions, mm.
        triangles: (F, 3) int32 vertex indices, counter-clockwise seen from outside where known.
        name: a human-readable identifier (file stem, or ``class/seed`` for built-in objects).
        label: the class name, if known.
        vertex_colors: optional (V, 3) float64 RGB in [0, 1].
        transform: 4 x 4 matrix mapping source coordinates to these (scale then translation).
        source: the file it came from, if any.

    Raises:
        InvalidMeshError: empty, non-finite or badly shaped arrays, or indices out of range.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    name: str = "object"
    label: str | None = None
    vertex_colors: np.ndarray | None = None
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    source: str | None = None

    def __post_init__(self) -> None:
        self.vertices, self.triangles = meshio.validate_arrays(self.vertices, self.triangles, self.name)
        if self.vertex_colors is not None:
            colors = np.asarray(self.vertex_colors, dtype=np.float64)
            if colors.shape != self.vertices.shape or not np.isfinite(colors).all():
                raise InvalidMeshError(
                    f"{self.name}: vertex_colors must be a finite ({len(self.vertices)}, 3) array, "
                    f"got shape {colors.shape}"
                )
            self.vertex_colors = np.clip(colors, 0.0, 1.0)
        self.transform = np.asarray(self.transform, dtype=np.float64).reshape(4, 4)

    # ----------------------------------------------------------------------------------------- basic
    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @property
    def has_colors(self) -> bool:
        return self.vertex_colors is not None

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner of the axis-aligned bounding box, mm."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @cached_property
    def center(self) -> np.ndarray:
        """Bounding-box centre, mm (the origin for loaded objects)."""
        return self.bounds.mean(axis=0)

    @cached_property
    def diagonal(self) -> float:
        """Bounding-box diagonal, mm."""
        return float(np.linalg.norm(self.bounds[1] - self.bounds[0]))

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        """(F,) triangle areas, mm^2."""
        return 0.5 * np.linalg.norm(self._face_cross, axis=1)

    @cached_property
    def triangle_normals(self) -> np.ndarray:
        """(F, 3) unit face normals (zero for degenerate faces)."""
        cross = self._face_cross
        norm = np.linalg.norm(cross, axis=1, keepdims=True)
        return np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)

    @cached_property
    def _face_cross(self) -> np.ndarray:
        v0, v1, v2 = (self.vertices[self.triangles[:, i]] for i in range(3))
        return np.cross(v1 - v0, v2 - v0)

    @cached_property
    def _directed_edges(self) -> np.ndarray:
        """(3F, 2) int64 directed edges of every triangle, in winding order."""
        t = self.triangles.astype(np.int64)
        return np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])

    def _edge_keys(self, pairs: np.ndarray) -> np.ndarray:
        # 1-D keys (i * V + j): ~10x faster to np.unique than (E, 2) rows with axis=0.
        return pairs[:, 0] * self.n_vertices + pairs[:, 1]

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) unique undirected edges, sorted per row."""
        keys = np.unique(self._edge_keys(np.sort(self._directed_edges, axis=1)))
        return np.stack([keys // self.n_vertices, keys % self.n_vertices], axis=1)

    @cached_property
    def is_watertight(self) -> bool:
        """True when every edge is shared by exactly two triangles, consistently oriented."""
        directed = self._directed_edges
        _, counts = np.unique(self._edge_keys(np.sort(directed, axis=1)), return_counts=True)
        # Consistent orientation: each directed edge appears once.
        return bool(np.all(counts == 2)) and len(np.unique(self._edge_keys(directed))) == len(directed)

    # ----------------------------------------------------------------------------------- derived
    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """(V, 3) unit vertex normals, mm-free, angle-weighted average of incident face normals.

        Angle weighting (Thürmer & Wüthrich) is the least sensitive to tessellation; see
        ``benchmarks/geometry.py`` for its error against the other estimators. Isolated vertices get (0, 0, 1).
        """
        return vertex_normals(self.vertices, self.triangles, method="angle")

    @cached_property
    def curvature(self) -> Curvature:
        """Per-vertex curvature from pymeshlab quadric fitting (the default estimator), 1/mm."""
        return self.compute_curvature("quadric")

    def compute_curvature(self, method: str = "quadric") -> Curvature:
        """Per-vertex curvature with the given estimator, cached per method.

        Args:
            method: one of :data:`perception.curvature.CURVATURE_METHODS`.

        Raises:
            ValueError: unknown method.
        """
        cache = self.__dict__.setdefault("_curvature_cache", {})
        if method not in cache:
            cache[method] = compute_curvature(self, method)
        return cache[method]

    @cached_property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """An Open3D ``RaycastingScene`` holding this mesh (geometry id 0), float32, mm."""
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)),
            o3d.core.Tensor(self.triangles.astype(np.uint32)),
        )
        return scene

    def to_open3d(self) -> o3d.geometry.TriangleMesh:
        """A legacy Open3D ``TriangleMesh`` copy (with vertex normals and colours)."""
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )
        mesh.vertex_normals = o3d.utility.Vector3dVector(self.vertex_normals)
        if self.vertex_colors is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors)
        return mesh

    def closest_points(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest surface points and unsigned distances (mm) for (N, 3) query points."""
        query = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        result = self.scene.compute_closest_points(query)
        closest = result["points"].numpy().astype(np.float64)
        return closest, np.linalg.norm(closest - np.asarray(points, dtype=np.float64).reshape(-1, 3), axis=1)

    def __repr__(self) -> str:
        return (
            f"ObjectModel(name={self.name!r}, label={self.label!r}, vertices={self.n_vertices}, "
            f"triangles={self.n_triangles}, diagonal={self.diagonal:.1f} mm)"
        )


def normalize(
    vertices: np.ndarray, size_mm: float = DEFAULT_SIZE_MM
) -> tuple[np.ndarray, np.ndarray]:
    """Centre on the bounding-box centre and scale to a bounding-box diagonal of ``size_mm``.

    Returns the new vertices and the 4 x 4 transform from the old coordinates to the new.

    Raises:
        InvalidMeshError: all vertices coincide (zero diagonal) or ``size_mm`` is not positive.
    """
    if not np.isfinite(size_mm) or size_mm <= 0:
        raise InvalidMeshError(f"size_mm must be a positive number of millimetres, got {size_mm!r}")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    if diagonal <= 0 or not np.isfinite(diagonal):
        raise InvalidMeshError("mesh has zero extent: all vertices coincide")
    scale = size_mm / diagonal
    center = 0.5 * (lo + hi)
    transform = np.eye(4)
    transform[:3, :3] *= scale
    transform[:3, 3] = -scale * center
    return (vertices - center) * scale, transform


def load_object(
    source: str | Path | o3d.geometry.TriangleMesh,
    *,
    label: str | None = None,
    size_mm: float | None = DEFAULT_SIZE_MM,
    repair: bool = True,
    name: str | None = None,
) -> ObjectModel:
    """Load a mesh file (OFF, OBJ, PLY, STL) or an Open3D mesh as a validated, repaired, scaled object.

    Polygon faces are fan-triangulated; texture colours (OBJ + MTL) become vertex colours. Repair
    (pymeshlab) merges duplicate vertices and removes duplicate and zero-area faces and unreferenced
    vertices; indices stay consistent because the arrays are rebuilt together.

    Args:
        source: a path or an ``open3d.geometry.TriangleMesh``.
        label: the class name to attach.
        size_mm: bounding-box diagonal after scaling, mm; ``None`` keeps the source scale and position.
        repair: run the pymeshlab clean-up (on by default).
        name: defaults to the file stem.

    Raises:
        MeshLoadError: missing, unreadable, unknown type, or unparseable file.
        InvalidMeshError: empty, non-finite, out-of-range indices, or nothing left after repair.
    """
    if isinstance(source, o3d.geometry.TriangleMesh):
        name = name or "open3d-mesh"
        vertices = np.asarray(source.vertices, dtype=np.float64)
        triangles = np.asarray(source.triangles, dtype=np.int64)
        colors = np.asarray(source.vertex_colors, dtype=np.float64) if source.has_vertex_colors() else None
        src = None
    else:
        path = Path(source)
        name = name or path.stem
        raw = meshio.read_mesh(path)
        vertices, triangles, colors = raw.vertices, raw.triangles, raw.vertex_colors
        src = str(path)
    where = src or name  # errors name the file when there is one
    vertices, triangles = meshio.validate_arrays(vertices, triangles, where)
    if repair:
        vertices, triangles, colors = meshio.repair(vertices, triangles, colors, where)
    transform = np.eye(4)
    if size_mm is not None:
        try:
            vertices, transform = normalize(vertices, size_mm)
        except InvalidMeshError as exc:
            raise InvalidMeshError(f"{where}: {exc}") from None
    return ObjectModel(
        vertices, triangles, name=name, label=label, vertex_colors=colors, transform=transform, source=src
    )


def load_dataset(folder: str | Path) -> list[tuple[Path, str]]:
    """List a class-per-subfolder mesh collection ``<root>/<Class>/<instance>.<ext>``.

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
        items.extend((p, class_dir.name) for p in files)
    return items
