"""Object geometry: the :class:`ObjectModel` every stage works on, and the frame it is put in.

Units are millimetres. Nothing here depends on how a file happens to be posed: a loaded object is centred on
its surface centroid (the area-weighted mean of its triangles) and scaled so that the sphere about that centre
holding every vertex has a diameter of ``size_mm`` (150 mm by default, a hand-held object). Both are
rotation-invariant, so a mesh and any rotation of it load to the same centre and size (the bounding box, the
paper's frame, changes with the pose: ``centering="bbox"`` keeps it as an option). ``ObjectModel.transform``
maps the source file's coordinates to the model's. Expensive derived data (normals, curvature, the ray-casting
scene) are computed on first use and cached, so a scene pays only for what it asks.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields, replace
from functools import cached_property

import numpy as np
import open3d as o3d

from perception import meshio
from perception.curvature import Curvature, compute_curvature, vertex_normals
from perception.errors import InvalidArgumentError, InvalidMeshError

log = logging.getLogger(__name__)

#: Default bounding-box diagonal of a loaded object, in millimetres.
DEFAULT_SIZE_MM = 150.0
#: An ObjectModel's coordinates stay within +-1e12 mm (products such as areas stay finite) and span at least
#: 1e-9 mm (areas and curvature do not underflow); load_object rescales anything to size_mm first.
MAX_COORDINATE_MM = 1e12
MIN_EXTENT_MM = 1e-9
_GEOMETRY_FIELDS = ("vertices", "triangles", "vertex_colors", "transform", "centering")
#: How an object's centre and size are defined: ``"surface"`` (pose-free: the area-weighted surface centroid and
#: the diameter of the sphere about it holding every vertex) or ``"bbox"`` (the paper's: the bounding-box centre
#: and diagonal, which change when the object is turned).
CENTERINGS = ("surface", "bbox")

@dataclass(eq=False)
class ObjectModel:
    """A triangle mesh in millimetres with lazily cached normals, curvature and ray-casting scene.

    Attributes:
        vertices: (V, 3) float64 positions, mm.
        triangles: (F, 3) int32 vertex indices, counter-clockwise seen from outside where known.
        name: a human-readable identifier (file stem, or ``class/seed`` for built-in objects).
        label: the class name, if known.
        vertex_colors: optional (V, 3) float64 RGB in [0, 1].
        transform: 4 x 4 matrix mapping source coordinates to these (rotation and scale, then translation).
        source: the file it came from, if any.
        centering: how :attr:`center` and :attr:`size` are defined, one of :data:`CENTERINGS` (default
            ``"surface"``, pose-free).

    The model keeps its own copies of the arrays. Assigning ``vertices``, ``triangles``, ``vertex_colors`` or
    ``transform`` re-validates and drops every cached value; editing the arrays in place is not supported
    (the caches would go stale): assign a new array or use ``dataclasses.replace``.

    Raises:
        InvalidMeshError: empty, non-finite or badly shaped arrays, indices out of range, or coordinates
            beyond +-``MAX_COORDINATE_MM`` or spanning less than ``MIN_EXTENT_MM`` (rescale on load).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    name: str = "object"
    label: str | None = None
    vertex_colors: np.ndarray | None = None
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    source: str | None = None
    centering: str = "surface"

    def __post_init__(self) -> None:
        check_centering(self.centering, self.name)
        vertices, triangles, colors, transform = self._checked(
            self.vertices, self.triangles, self.vertex_colors, self.transform
        )
        for key, value in (("vertices", vertices), ("triangles", triangles), ("vertex_colors", colors)):
            object.__setattr__(self, key, value)
        object.__setattr__(self, "transform", transform)
        object.__setattr__(self, "_ready", True)

    def _checked(self, vertices, triangles, colors, transform):
        """Validated copies (the model never shares arrays with the caller, so later edits of the caller's
        arrays cannot make the caches stale)."""
        vertices, triangles = meshio.validate_arrays(vertices, triangles, self.name)
        vertices, triangles = vertices.copy(), triangles.copy()
        extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
        if float(np.abs(vertices).max()) > MAX_COORDINATE_MM or 0 < extent < MIN_EXTENT_MM:
            raise InvalidMeshError(
                f"{self.name}: coordinates must lie within +-{MAX_COORDINATE_MM:g} mm and span at least "
                f"{MIN_EXTENT_MM:g} mm (got max |x| {float(np.abs(vertices).max()):.3g} mm, extent {extent:.3g} mm); "
                "load_object(..., size_mm=...) rescales"
            )
        if colors is not None:
            colors = np.asarray(colors, dtype=np.float64)
            if colors.shape != vertices.shape or not np.isfinite(colors).all():
                raise InvalidMeshError(
                    f"{self.name}: vertex_colors must be a finite ({len(vertices)}, 3) array, "
                    f"got shape {colors.shape}"
                )
            colors = np.clip(colors, 0.0, 1.0)
        transform = np.array(transform, dtype=np.float64)
        if transform.size != 16 or not np.isfinite(transform).all():
            raise InvalidMeshError(f"{self.name}: transform must be a finite 4 x 4 matrix, got shape {transform.shape}")
        return vertices, triangles, colors, transform.reshape(4, 4)

    def __setattr__(self, key: str, value) -> None:
        """Assigning ``vertices``, ``triangles``, ``vertex_colors`` or ``transform`` re-validates and drops every
        cached derived value (bounds, normals, curvature, scene). To change vertices and triangles together,
        build a new model (``dataclasses.replace(model, vertices=..., triangles=...)``). Arrays must not be
        edited in place: the caches would not know."""
        if not self.__dict__.get("_ready") or key not in _GEOMETRY_FIELDS:
            object.__setattr__(self, key, value)
            return
        if key == "centering":
            check_centering(value, self.name)
        current = {k: self.__dict__[k] for k in _GEOMETRY_FIELDS}
        current[key] = value
        checked = self._checked(current["vertices"], current["triangles"], current["vertex_colors"], current["transform"])
        for k in [k for k in self.__dict__ if k not in _FIELD_NAMES and k != "_ready"]:
            del self.__dict__[k]
        for k, v in zip(("vertices", "triangles", "vertex_colors", "transform"), checked, strict=True):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "centering", current["centering"])

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
        """The object's centre, mm (the origin for loaded objects; contour planes pass through it): the area-
        weighted surface centroid (``centering="surface"``, follows the object when it is turned; the mean
        vertex where every triangle has zero area) or the bounding-box centre (``"bbox"``)."""
        if self.centering == "bbox":
            return self.bounds.mean(axis=0)
        return surface_centroid(self.vertices, self.triangles)

    @cached_property
    def size(self) -> float:
        """The object's size, mm, what ``load_object(size_mm=...)`` scales to: the diameter of the sphere about
        :attr:`center` holding every vertex (``centering="surface"``, unchanged when the object is turned) or
        the bounding-box diagonal (``"bbox"``). Scale-dependent settings (saliency spacing, views) use it."""
        if self.centering == "bbox":
            return self.diagonal
        return 2.0 * _max_norm(self.vertices - self.center)

    @cached_property
    def diagonal(self) -> float:
        """Bounding-box diagonal, mm."""
        return _norm3(self.bounds[1] - self.bounds[0])

    @cached_property
    def principal_frame(self) -> np.ndarray:
        """(3, 3) rotation whose columns are the surface's principal axes about :attr:`center`, largest
        second moment first, each signed so that the surface's third moment along it is positive; turning the
        object turns the frame with it. A pose-free frame for what must look at the object from fixed
        directions (saliency views). Where two moments are equal (surfaces of revolution) the axes in their
        plane are any orthonormal pair, a choice the object's symmetry makes (nearly) irrelevant."""
        return principal_frame(self.vertices, self.triangles, self.center)

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        """(F,) triangle areas, mm^2."""
        return 0.5 * np.linalg.norm(self._face_cross, axis=1)

    @cached_property
    def triangle_normals(self) -> np.ndarray:
        """(F, 3) unit face normals (zero for degenerate faces)."""
        cross = self._face_cross
        # Scaled to a largest component of 1 first: the squares of a cross product of 1e-200 underflow.
        top = np.abs(cross).max(axis=1, keepdims=True)
        cross = np.divide(cross, top, out=np.zeros_like(cross), where=top > 0)
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
            InvalidArgumentError: unknown method.
        """
        cache = self.__dict__.setdefault("_curvature_cache", {})
        if method not in cache:
            cache[method] = compute_curvature(self, method)
        return cache[method]

    @cached_property
    def scene_origin(self) -> np.ndarray:
        """(3,) float64 point the ray-casting scene is built around, mm: :attr:`center` (see :meth:`to_scene`)."""
        return self.center.copy()

    def to_scene(self, vectors: np.ndarray, *, directions: bool = False) -> np.ndarray:
        """Points (mm) or, with ``directions=True``, directions in the ray-casting scene's frame, float64: about
        :attr:`scene_origin`, along :attr:`principal_frame`. That frame turns with the object, so a mesh and any
        rotation of it round to the same float32 scene and rays built in it to the same float32 rays: what is cast
        does not depend on the pose, and a mesh far from the origin keeps its float32 precision."""
        vectors = np.asarray(vectors, dtype=np.float64)
        return (vectors if directions else vectors - self.scene_origin) @ self.principal_frame

    def from_scene(self, points: np.ndarray) -> np.ndarray:
        """Points (mm) from the scene's frame back to the model's, float64 (the inverse of :meth:`to_scene`)."""
        return np.asarray(points, dtype=np.float64) @ self.principal_frame.T + self.scene_origin

    @cached_property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """An Open3D ``RaycastingScene`` holding this mesh (geometry id 0), float32, mm, in the scene's frame
        (:meth:`to_scene`: about the centre, along the principal axes). Cast rays made with :meth:`to_scene`
        and map hit points back with :meth:`from_scene`; distances and triangle ids need nothing."""
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(self.to_scene(self.vertices).astype(np.float32)),
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
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        query = o3d.core.Tensor(self.to_scene(points).astype(np.float32))
        result = self.scene.compute_closest_points(query)
        closest = self.from_scene(result["points"].numpy())
        return closest, np.linalg.norm(closest - points, axis=1)

    def __repr__(self) -> str:
        return (
            f"ObjectModel(name={self.name!r}, label={self.label!r}, vertices={self.n_vertices}, "
            f"triangles={self.n_triangles}, diagonal={self.diagonal:.1f} mm)"
        )


_FIELD_NAMES = frozenset(f.name for f in fields(ObjectModel))


def check_centering(centering: str, where: str = "object") -> None:
    """Raise :class:`InvalidArgumentError` unless ``centering`` is one of :data:`CENTERINGS`."""
    if centering not in CENTERINGS:
        raise InvalidArgumentError(f"{where}: centering must be one of {', '.join(CENTERINGS)}, got {centering!r}")


def surface_centroid(vertices: np.ndarray, triangles: np.ndarray | None = None) -> np.ndarray:
    """(3,) area-weighted centroid of the triangles' surface, mm; the mean vertex when there are no triangles or
    all have zero area. It follows the mesh under any rotation and translation and, unlike the mean vertex, does
    not depend on how finely each part is tessellated. Coordinates up to +-1e12 mm stay finite."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if triangles is not None and len(triangles):
        v0, v1, v2 = (vertices[triangles[:, i]] for i in range(3))
        # Relative to the mean vertex: smaller numbers, so the products below lose less to rounding.
        origin = vertices.mean(axis=0)
        areas = np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)
        total = areas.sum()
        if total > 0 and np.isfinite(total):
            centroids = (v0 + v1 + v2) / 3.0 - origin
            return origin + (areas @ centroids) / total
    return vertices.mean(axis=0)


def principal_frame(vertices: np.ndarray, triangles: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(3, 3) proper rotation, columns the principal axes of the triangles' surface about ``center`` (see
    :attr:`ObjectModel.principal_frame`). Second moments are exact per triangle
    (integral of x x^T over a triangle = area / 12 (sum_i v_i v_i^T + s s^T), s = v0 + v1 + v2); signs come from
    the third moments of the triangle centroids. Degenerate inputs (no area) give the identity."""
    v = (np.asarray(vertices, dtype=np.float64) - center)
    scale = max(_max_norm(v), 1e-300)
    v = v / scale  # unit size: the moments neither overflow nor underflow
    v0, v1, v2 = (v[triangles[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)
    if not areas.sum() > 0:
        return np.eye(3)
    total = v0 + v1 + v2
    second = np.einsum("f,fi,fj->ij", areas, total, total)
    for corner in (v0, v1, v2):
        second += np.einsum("f,fi,fj->ij", areas, corner, corner)
    _, axes = np.linalg.eigh(second / 12.0)  # ascending
    axes = axes[:, ::-1].copy()
    third = areas @ ((total / 3.0) @ axes) ** 3
    axes *= np.where(third < 0, -1.0, 1.0)
    axes[:, 2] = np.cross(axes[:, 0], axes[:, 1])  # right-handed: a proper rotation
    return axes


def random_rotation(seed: int | np.random.Generator) -> np.ndarray:
    """(3, 3) rotation matrix drawn uniformly over SO(3) (Haar measure) from ``seed``: same seed, same bytes."""
    from scipy.spatial.transform import Rotation

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return Rotation.random(random_state=rng).as_matrix()


def rescale(model: ObjectModel, size_mm: float = DEFAULT_SIZE_MM, *, name: str | None = None) -> ObjectModel:
    """A copy of ``model`` centred and scaled to ``size_mm`` in its pose-free frame (:func:`normalize` with its
    triangles), e.g. a camera reconstruction (physical mm) brought to the size a classifier was trained at;
    ``transform`` maps the model's coordinates to the copy's.

    Raises:
        InvalidArgumentError: ``size_mm`` is not a positive number.
    """
    vertices, scaling = normalize(model.vertices, size_mm, triangles=model.triangles, centering=model.centering)
    return replace(model, vertices=vertices, transform=scaling @ model.transform, name=name or model.name)


def rotate(model: ObjectModel, rotation: np.ndarray) -> ObjectModel:
    """A copy of ``model`` turned by the (3, 3) ``rotation`` about its :attr:`~ObjectModel.center` (the centre
    stays; ``transform`` records the turn). Presents an object in another pose without reloading it.

    Raises:
        InvalidArgumentError: ``rotation`` is not a proper rotation matrix.
    """
    r = _check_rotation(rotation, model.name)
    turn = np.eye(4)
    turn[:3, :3] = r
    turn[:3, 3] = model.center - r @ model.center
    return replace(model, vertices=model.vertices @ r.T + turn[:3, 3], transform=turn @ model.transform)


def _check_rotation(rotation, where: str) -> np.ndarray:
    """``rotation`` as a float64 proper rotation matrix (orthonormal to 1e-6, determinant +1)."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise InvalidArgumentError(f"{where}: rotation must be a finite 3 x 3 matrix, got shape {r.shape}")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
        raise InvalidArgumentError(
            f"{where}: rotation must be orthonormal with determinant +1 (a proper rotation), got {r.tolist()}"
        )
    return r


def _max_norm(vectors: np.ndarray) -> float:
    """Largest Euclidean length of (N, 3) vectors without overflow (scaled by the largest component first)."""
    top = float(np.abs(vectors).max()) if len(vectors) else 0.0
    if top == 0:
        return 0.0
    return top * float(np.sqrt(((vectors / top) ** 2).sum(axis=1).max()))


def _norm3(vector: np.ndarray) -> float:
    """Euclidean length of a 3-vector without overflow (hypot scales): finite for any finite input."""
    return float(np.hypot(np.hypot(vector[0], vector[1]), vector[2]))


def normalize(
    vertices: np.ndarray,
    size_mm: float = DEFAULT_SIZE_MM,
    *,
    triangles: np.ndarray | None = None,
    centering: str = "surface",
) -> tuple[np.ndarray, np.ndarray]:
    """Centre and scale ``vertices`` to an object of size ``size_mm`` in a frame that does not depend on the pose.

    ``centering="surface"``: centre on the area-weighted centroid of ``triangles`` (the mean vertex for a point
    set, ``triangles=None``) and scale so that the sphere about it holding every vertex has diameter ``size_mm``;
    turning the input turns the output and changes neither. ``"bbox"`` (the paper's): centre on the bounding-box
    centre and scale to a bounding-box diagonal of ``size_mm``; both change with the pose.

    Returns the new vertices and the 4 x 4 transform from the old coordinates to the new. Works for any
    finite coordinates (a bounding-box pre-scaling comes first, so +-1e308 does not overflow).

    Raises:
        InvalidMeshError: all vertices coincide (zero extent). InvalidArgumentError: ``size_mm`` is not a positive
            number.
        InvalidArgumentError: an unknown ``centering``.
    """
    check_centering(centering, "normalize")
    if isinstance(size_mm, bool) or not isinstance(size_mm, (int, float, np.floating, np.integer)):
        raise InvalidArgumentError(f"size_mm must be a positive number of millimetres, got {size_mm!r}")
    if not np.isfinite(size_mm) or not 0 < size_mm <= MAX_COORDINATE_MM:
        raise InvalidArgumentError(f"size_mm must be a positive number of millimetres up to {MAX_COORDINATE_MM:g}, "
                                   f"got {size_mm!r}")
    vertices = np.asarray(vertices, dtype=np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    half_extent = 0.5 * hi - 0.5 * lo
    half_diagonal = _norm3(half_extent)
    if half_diagonal <= 0:
        raise InvalidMeshError("mesh has zero extent: all vertices coincide")
    # Step 1 (both rules): bounding-box centre and a diagonal of 2, computed on halves so nothing overflows.
    center = 0.5 * lo + 0.5 * hi
    scale = 1.0 / half_diagonal
    unit = (0.5 * vertices - 0.5 * center) * (2.0 * scale)
    if centering == "surface":
        # Step 2: a similarity maps centroids to centroids, so the composite is exactly the pose-free frame.
        shift = surface_centroid(unit, triangles)
        radius = _max_norm(unit - shift)
        center, scale = center + shift / scale, scale / radius
        unit = (unit - shift) / radius  # enclosing-sphere diameter 2
    factor = 0.5 * float(size_mm)
    out = unit * factor
    transform = np.eye(4)
    transform[:3, :3] *= scale * factor
    transform[:3, 3] = -scale * factor * center
    if not (np.isfinite(out).all() and np.isfinite(transform).all()):
        raise InvalidMeshError(f"mesh extent {2 * half_diagonal:.3g} cannot be scaled to {size_mm} mm")
    return out, transform


def text_name(name: str) -> str:
    """A file or folder name as text that encodes to UTF-8: bytes that are not UTF-8 (a name Python decoded with
    surrogate escapes) become ``\\xNN``, so names made from any file name can be printed, hashed and stored.

    Examples:
        >>> text_name("mug")
        'mug'
        >>> text_name("mug\\udcff")  # os.fsdecode(b"mug\\xff")
        'mug\\\\xff'
    """
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


#: Names that moved to :mod:`perception.loading` (objects arriving from files), still importable from here.
_LOADING = ("list_collection", "load_dataset", "load_object")


def __getattr__(name: str):
    # The loaders live in perception.loading (imported on first use: it imports this module).
    if name in _LOADING:
        from perception import loading

        return getattr(loading, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
