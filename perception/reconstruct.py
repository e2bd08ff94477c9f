"""Point clouds and RGB-D captures -> surfaces -> :class:`~perception.geometry.ObjectModel`.

Two entry points:

- :func:`load_points`: a point-cloud file (PCD, XYZ/XYZN/XYZRGB/PTS, PLY, NPY/NPZ) or an
  ``open3d.geometry.PointCloud`` -> outliers removed -> normals estimated and oriented -> surface
  (screened Poisson trimmed by density; ball pivoting or alpha shapes as alternatives) -> ``ObjectModel``.
- :func:`reconstruct_frames`: RGB-D frames (:mod:`perception.camera`) -> points in the world frame ->
  table plane removed (RANSAC) -> objects clustered (DBSCAN) -> the chosen object's views fused (known poses,
  ICP refinement) -> the same surface step, closed where no camera saw it (the bottom on the table) from
  the space the frames carved (:func:`carve`), so the model stands in for a CAD mesh: watertight, with the
  CAD mesh's centre and size.

Units are millimetres. Every random choice (RANSAC) is seeded and Poisson runs on one thread, so the same
input and seed give the same bytes.
"""

from __future__ import annotations

import logging
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from perception import meshio
from perception.errors import InvalidArgumentError, InvalidMeshError, MeshLoadError
from perception.geometry import DEFAULT_SIZE_MM, ObjectModel, normalize

log = logging.getLogger(__name__)

#: File suffixes :func:`read_points` understands.
POINT_SUFFIXES = frozenset({".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt", ".ply", ".npy", ".npz"})
#: Fewer points than this cannot support a surface.
MIN_POINTS = 30
#: A cloud whose second (third) principal extent is below this fraction of the first is a line (plane).
FLAT_RATIO = 1e-3
#: Surface methods of :func:`surface_from_points`.
METHODS = ("poisson", "ball_pivoting", "alpha")
#: Surface pieces with fewer triangles than this fraction of the largest piece are dropped as specks.
MIN_PIECE = 0.05
#: Default alpha of alpha shapes, as a fraction of the cloud's bounding-box diagonal.
ALPHA_FRACTION = 0.2
#: A closed reconstruction with more than this fraction of its vertices outside the carved space (grown
#: by two voxels) has leaked: Poisson extrapolated a thin shell seen on one side (:func:`reconstruct_frames`).
LEAK_FRACTION = 0.01
#: Normals are oriented consistently on at most this many points, then copied to their neighbours. The
#: subsample must be denser than thin walls are thick: at 4,000 points (spacing ~4 mm) the 3 mm wall of a
#: catalogue mug got 43 % of its normals flipped; at 15,000 none (1.7 s CPU).
_ORIENT_POINTS = 20000


# ------------------------------------------------------------------------------------------- files
# PCD and PLY are parsed here, not by Open3D: on a short or malformed file its readers return the declared
# number of points, the unread ones zero or uninitialised (a truncated ASCII PCD "loads"), and its PLY
# reader can segfault. Only compressed binary PCD (LZF) still goes to Open3D, which checks its sizes.
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def _too_many(path: Path, count: int, size: int) -> MeshLoadError:
    return MeshLoadError(f"{path}: header announces {count} points, more than the {size}-byte file holds")


def _read_pcd(path: Path, data: bytes) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    header: dict[str, list[str]] = {}
    pos = 0
    while "DATA" not in header:
        end = data.find(b"\n", pos)
        if end < 0:
            raise MeshLoadError(f"{path}: no points could be read (not a PCD file: no DATA line)")
        words = data[pos:end].decode("latin-1").split()
        pos = end + 1
        if words and not words[0].startswith("#"):
            header[words[0].upper()] = words[1:]
    try:
        fields, types = header["FIELDS"], [t.upper() for t in header["TYPE"]]
        sizes = [int(s) for s in header["SIZE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        n = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        dtypes = [_PCD_TYPES[t, s] for t, s in zip(types, sizes, strict=True)]
        mode = header["DATA"][0].lower()
        if len(counts) != len(fields) or min(counts) < 1 or n < 0 or not {"x", "y", "z"} <= set(fields):
            raise ValueError
    except (KeyError, ValueError, IndexError):
        raise MeshLoadError(f"{path}: no points could be read (bad PCD header: FIELDS with x y z, SIZE, TYPE, "
                            "COUNT, POINTS and DATA expected)") from None
    starts = [int(s) for s in np.cumsum([0, *counts])]
    if mode == "ascii":
        if n * 2 * starts[-1] > len(data) - pos:  # a value takes a character and a separator at least
            raise _too_many(path, n, len(data))
        try:
            rows = [ln.split() for ln in data[pos:].decode("ascii").splitlines() if ln.strip()]
            if len(rows) != n or any(len(r) != starts[-1] for r in rows):
                raise ValueError
            table = np.array(rows, dtype=np.float64).reshape(n, starts[-1])
        except (UnicodeDecodeError, ValueError):
            raise MeshLoadError(f"{path}: PCD data must be {n} lines of {starts[-1]} numbers (truncated or corrupt)") from None
        columns = {f: table[:, a:b] for f, a, b in zip(fields, starts, starts[1:])}
    elif mode == "binary":
        layout = np.dtype([(f"f{i}", "<" + d, (c,)) for i, (d, c) in enumerate(zip(dtypes, counts))])
        if n * layout.itemsize > len(data) - pos:
            raise _too_many(path, n, len(data))
        rows = np.frombuffer(data, layout, n, pos)
        columns = {f: rows[f"f{i}"] for i, f in enumerate(fields)}
    else:
        cloud = o3d.io.read_point_cloud(str(path), format="pcd")
        points = np.asarray(cloud.points, dtype=np.float64)
        if len(points) != n or n == 0:
            raise MeshLoadError(f"{path}: no points could be read ({mode} PCD, {len(points)} of {n} points)")
        return (points, np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None,
                np.asarray(cloud.colors, dtype=np.float64) if cloud.has_colors() else None)
    points = np.column_stack([columns[c][:, 0] for c in "xyz"]).astype(np.float64)
    normals = colors = None
    if {"normal_x", "normal_y", "normal_z"} <= set(columns):
        normals = np.column_stack([columns[f"normal_{c}"][:, 0] for c in "xyz"]).astype(np.float64)
    for name in ("rgb", "rgba"):  # PCL packs 8-bit R, G, B into the bits of one float (or an unsigned int)
        if name in columns:
            value = columns[name][:, 0]
            with np.errstate(invalid="ignore", over="ignore"):
                bits = value.astype(np.float32).view(np.uint32) if types[fields.index(name)] == "F" else value.astype(np.uint32)
            colors = np.column_stack([(bits >> s) & 255 for s in (16, 8, 0)]).astype(np.float64) / 255.0
            break
    return points, normals, colors


def _read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    vertex = meshio.read_ply(path).get("vertex", {})
    if not {"x", "y", "z"} <= set(vertex):
        raise MeshLoadError(f"{path}: no points could be read (no vertex element with x, y, z)")
    points = np.column_stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"])
    normals = colors = None
    if {"nx", "ny", "nz"} <= set(vertex):
        normals = np.column_stack([np.asarray(vertex[c], dtype=np.float64) for c in ("nx", "ny", "nz")])
    if {"red", "green", "blue"} <= set(vertex):
        rgb = [np.asarray(vertex[c]) for c in ("red", "green", "blue")]
        colors = np.column_stack(rgb).astype(np.float64)
        if rgb[0].dtype.kind in "iu":
            colors /= float(np.iinfo(rgb[0].dtype).max)
    return points, normals, colors


def _read_text(path: Path, text: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    rows = [ln.split("#", 1)[0].replace(",", " ").split() for ln in text.splitlines()]
    rows = [r for r in rows if r]
    if rows and len(rows[0]) == 1 and path.suffix.lower() == ".pts":  # PTS: first line is the count
        rows = rows[1:]
    if not rows:
        return np.zeros((0, 3)), None, None
    width = len(rows[0])
    bad = next((i for i, r in enumerate(rows) if len(r) != width), None)
    if width < 3 or bad is not None:
        line = 0 if width < 3 else bad
        raise MeshLoadError(
            f"{path}: line {line + 1} of the point data has {len(rows[line])} values; "
            f"every line needs the same number, at least x y z"
        )
    try:
        table = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise MeshLoadError(f"{path}: point data is not numeric ({exc})") from None
    points, normals, colors = table[:, :3], None, None
    suffix = path.suffix.lower()
    if suffix == ".xyzn" and width >= 6:
        normals = table[:, 3:6]
    elif suffix == ".xyzrgb" and width >= 6:
        colors = table[:, 3:6]
        colors = colors / 255.0 if colors.max(initial=0) > 1 else colors
    return points, normals, colors


def _npy(stream, available: int, where: str) -> np.ndarray:
    """An array from an NPY stream, after checking that its header's shape fits the ``available`` bytes
    (``np.load`` allocates the declared shape first: a doctored header asks for terabytes)."""
    version = np.lib.format.read_magic(stream)
    start = stream.tell()
    read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    if version not in read_header:
        raise ValueError(f"{where}: NPY format version {version} is not supported")
    shape, fortran, dtype = read_header[version](stream)
    if dtype.hasobject or not np.issubdtype(dtype, np.number):
        raise ValueError(f"{where}: {dtype} is not a numeric array")
    count = 1
    for d in shape:  # Python integers: no overflow
        count *= d
    if min(shape, default=0) < 0 or count * dtype.itemsize > available - (stream.tell() - start) - 8:
        raise ValueError(f"{where}: header declares shape {shape}, more than the file holds")
    data = stream.read(count * dtype.itemsize)
    if len(data) != count * dtype.itemsize:
        raise ValueError(f"{where}: truncated")
    return np.frombuffer(data, dtype, count).reshape(shape, order="F" if fortran else "C")


def _read_arrays(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    normals = colors = None
    try:
        if path.suffix.lower() == ".npy":
            with path.open("rb") as f:
                table = _npy(f, path.stat().st_size, "array")
            if table.ndim == 2 and table.shape[1] >= 6:
                normals = table[:, 3:6]
        else:
            with zipfile.ZipFile(path) as archive:
                infos = {i.filename.removesuffix(".npy"): i for i in archive.infolist()}
                keys = list(infos)
                key = next((k for k in ("points", "xyz", "vertices") if k in keys), keys[0] if len(keys) == 1 else None)
                if key is None:
                    raise MeshLoadError(f"{path}: no 'points' array among {keys}")

                def member(name: str) -> np.ndarray:
                    with archive.open(infos[name]) as f:
                        return _npy(f, infos[name].file_size, name)

                table = member(key)
                normals = member("normals") if "normals" in keys else None
                colors = member("colors") if "colors" in keys else None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError) as exc:
        raise MeshLoadError(f"{path}: not a numpy file, or a corrupt one ({type(exc).__name__}: {exc})") from None
    if table.ndim != 2 or table.shape[1] < 3:
        raise MeshLoadError(f"{path}: points must be a numeric (N, 3) array, got {table.dtype} {table.shape}")
    return table[:, :3].astype(np.float64), normals, colors


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a point-cloud file: (N, 3) points and optional (N, 3) normals and RGB colours in [0, 1].

    Every format is parsed here, strictly (Open3D's readers skip bad lines and return unread points as
    zeros; only LZF-compressed PCD goes to Open3D); a PLY's faces, if any, are ignored (the vertices are
    the points). ``.xyz``/``.txt``/``.pts``
    take the first three columns, ``.xyzn`` adds normals, ``.xyzrgb`` colours. NPY holds an (N, 3) or
    (N, 6: points, normals) array; NPZ a ``points`` (or ``xyz``) array with optional ``normals``/``colors``.

    Raises:
        MeshLoadError: missing, empty, unknown type, or unparseable file.
    """
    path, suffix = meshio.check_file(path, "point-cloud", POINT_SUFFIXES)
    if suffix in (".npy", ".npz"):
        return _read_arrays(path)
    data = path.read_bytes()
    if suffix in (".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt"):
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError:
            raise MeshLoadError(f"{path}: not an ASCII point file (binary or corrupt content)") from None
        return _read_text(path, text)
    points, normals, colors = _read_pcd(path, data) if suffix == ".pcd" else _read_ply_points(path)
    if len(points) == 0:
        raise MeshLoadError(f"{path}: no points could be read (an empty {suffix[1:].upper()} file)")
    return points, normals, colors


def write_points(path: str | Path, points: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """Write (N, 3) points (mm) and optional normals atomically; format from the suffix (PCD, PLY, XYZ,
    XYZN, NPY, NPZ). Text formats keep 17 significant digits, so float64 values round-trip exactly.

    Raises:
        MeshLoadError: unknown suffix.
        InvalidMeshError: bad point array (see :func:`validate_points`, without the size and shape checks).
    """
    from perception.atomic import atomic_path

    path = Path(path)
    points = _as_points(points, str(path))
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix in (".xyz", ".xyzn", ".txt", ".pts"):
            table = points if normals is None or suffix != ".xyzn" else np.hstack([points, normals])
            np.savetxt(tmp, table, fmt="%.17g")
        elif suffix == ".npy":
            np.save(tmp, points)
        elif suffix == ".npz":
            extra = {} if normals is None else {"normals": np.asarray(normals, dtype=np.float64)}
            np.savez(tmp, points=points, **extra)
        elif suffix in (".pcd", ".ply"):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            if normals is not None:
                cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
            if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
                raise MeshLoadError(f"{path}: Open3D could not write the point cloud")
        else:
            raise MeshLoadError(f"{path}: unknown point-cloud type {suffix!r}")
    return path


# -------------------------------------------------------------------------------------- validation
def _as_points(points, name: str) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3 or not np.issubdtype(p.dtype, np.number):
        raise InvalidMeshError(f"{name}: points must be a numeric (N, 3) array, got shape {p.shape}")
    p = p.astype(np.float64)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise InvalidMeshError(
            f"{name}: {int(bad.sum())} points are NaN or Inf (first at index {int(np.argmax(bad))}); "
            "drop them before loading"
        )
    return p


def validate_points(points, name: str = "point cloud", min_points: int = MIN_POINTS) -> np.ndarray:
    """Check a cloud can carry a surface; return it as float64 (N, 3).

    Raises:
        InvalidMeshError: not (N, 3), empty, NaN/Inf, fewer than ``min_points`` distinct points, or all
            points on a line or a plane (second / third principal extent below ``FLAT_RATIO`` of the first).
    """
    p = _as_points(points, name)
    if len(p) == 0:
        raise InvalidMeshError(f"{name}: the point cloud is empty")
    distinct = len(np.unique(p, axis=0))
    if distinct < min_points:
        raise InvalidMeshError(
            f"{name}: only {distinct} distinct points; a surface needs at least {min_points}"
        )
    spread = np.linalg.svd(p - p.mean(axis=0), compute_uv=False) / np.sqrt(len(p))
    if spread[1] <= FLAT_RATIO * spread[0]:
        raise InvalidMeshError(f"{name}: all points lie on a line; a surface needs a 3D cloud")
    if spread[2] <= FLAT_RATIO * spread[0]:
        raise InvalidMeshError(f"{name}: all points lie on a plane; a closed surface needs a 3D cloud")
    return p


# ----------------------------------------------------------------------------------------- normals
def mean_spacing(points: np.ndarray) -> float:
    """Mean distance from each point to its nearest neighbour, mm."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    d = np.asarray(cloud.compute_nearest_neighbor_distance())
    d = d[d > 0]
    return float(d.mean()) if len(d) else 0.0


def estimate_normals(
    points: np.ndarray, *, k: int = 20, viewpoints: np.ndarray | None = None, seed: int = 0
) -> np.ndarray:
    """Unit normals by local PCA over ``k`` neighbours (Open3D), oriented.

    Orientation: towards each point's viewpoint when ``viewpoints`` ((N, 3) or (3,) camera centres, mm)
    are known (the reliable case for camera data); otherwise consistently over a tangent-plane graph
    (Open3D) on at most ``_ORIENT_POINTS`` points, copied to the rest from their nearest oriented point,
    and flipped as a whole so that sum(n . (p - centroid)) > 0 (positive for an outward-oriented closed
    surface: it integrates to three times the enclosed volume).
    """
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    normals = np.asarray(cloud.normals).copy()
    if viewpoints is not None:
        to_view = np.broadcast_to(np.asarray(viewpoints, dtype=np.float64), points.shape) - points
        flip = (normals * to_view).sum(axis=1) < 0
        normals[flip] *= -1
        return normals
    n = len(points)
    pick = np.arange(n) if n <= _ORIENT_POINTS else np.random.default_rng(seed).choice(n, _ORIENT_POINTS, replace=False)
    pick.sort()
    sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[pick]))
    sub.normals = o3d.utility.Vector3dVector(normals[pick])
    try:
        sub.orient_normals_consistent_tangent_plane(min(k, max(3, len(pick) - 1)))
    except RuntimeError as exc:  # Qhull refuses degenerate (e.g. exactly cospherical) input
        log.warning("consistent normal orientation failed (%s); orienting away from the centroid", str(exc)[:80])
        centroid = points[pick].mean(axis=0)
        sub.orient_normals_towards_camera_location(centroid)
        sub.normals = o3d.utility.Vector3dVector(-np.asarray(sub.normals))
    oriented = np.asarray(sub.normals)
    if (oriented * (points[pick] - points[pick].mean(axis=0))).sum() < 0:
        oriented = -oriented
    tree = o3d.geometry.KDTreeFlann(sub)
    nearest = np.array([tree.search_knn_vector_3d(p, 1)[1][0] for p in points]) if n != len(pick) else np.arange(n)
    flip = (normals * oriented[nearest]).sum(axis=1) < 0
    normals[flip] *= -1
    return normals


def _clean(points, normals, colors, nb: int, std: float):
    """Statistical outlier removal (Open3D); returns the kept rows of all arrays."""
    if nb <= 0 or len(points) <= nb:
        return points, normals, colors
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, kept = cloud.remove_statistical_outlier(nb_neighbors=nb, std_ratio=std)
    kept = np.asarray(kept, dtype=np.int64)
    pick = lambda a: None if a is None else np.asarray(a)[kept]
    return points[kept], pick(normals), pick(colors)


# ----------------------------------------------------------------------------------------- surface
def surface_from_points(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    method: str = "poisson",
    poisson_depth: int = 8,
    density_trim: float | None = 1.0,
    max_triangles: int | None = 20000,
    alpha_mm: float | None = None,
    name: str = "point cloud",
) -> tuple[np.ndarray, np.ndarray]:
    """A triangle surface through oriented points: (V, 3) vertices (mm) and (F, 3) triangles.

    ``poisson``: screened Poisson (Kazhdan & Hoppe 2013, Open3D, one thread: deterministic), trimmed by
    density as PoissonRecon's SurfaceTrimmer does: Poisson closes holes with surface far from any sample,
    and there the density (the octree depth of the supporting samples) drops; vertices more than
    ``density_trim`` levels below the 90th percentile of the densities are removed (about one level
    separates extrapolated surface from sampled surface; ``None`` keeps the closed surface). ``ball_pivoting``: radii 1, 2, 4 times
    the mean point spacing. ``alpha``: alpha shape (normals unused) with ``alpha_mm``, by default
    ``ALPHA_FRACTION`` of the cloud's bounding-box diagonal (alpha shapes need alpha above the largest gap
    between samples: on 6k random samples of a catalogue box, 15 % of the diagonal left holes, 20 % none).
    Pieces under ``MIN_PIECE`` of the largest one are dropped and, above ``max_triangles``, the surface is
    simplified by quadric decimation.

    Raises:
        InvalidArgumentError: unknown method or bad parameter.
        InvalidMeshError: no surface could be built.
    """
    if method not in METHODS:
        raise InvalidArgumentError(f"{name}: unknown surface method {method!r}; choose one of {', '.join(METHODS)}")
    if not (isinstance(poisson_depth, (int, np.integer)) and 4 <= poisson_depth <= 12):
        raise InvalidArgumentError(f"{name}: poisson_depth must be an integer in 4..12, got {poisson_depth!r}")
    if density_trim is not None and not (np.isfinite(density_trim) and density_trim > 0):
        raise InvalidArgumentError(f"{name}: density_trim must be a positive number of octree levels or None")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    spacing = mean_spacing(points)
    if method == "poisson":
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=int(poisson_depth), n_threads=1
        )
        density = np.asarray(density)
        if density_trim is not None and len(density):
            mesh.remove_vertices_by_mask(density < np.quantile(density, 0.9) - density_trim)
        # Open3D's Poisson can emit a face twice (both windings) where two sheets meet in a thin wall:
        # four faces on each of its edges. The pair encloses nothing; dropping both keeps the rest closed.
        faces = np.sort(np.asarray(mesh.triangles), axis=1)
        if len(faces):
            _, inverse, counts = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
            mesh.remove_triangles_by_mask(counts[inverse.ravel()] > 1)
    elif method == "ball_pivoting":
        radii = o3d.utility.DoubleVector([spacing, 2 * spacing, 4 * spacing])
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    else:
        diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
        alpha = ALPHA_FRACTION * diagonal if alpha_mm is None else float(alpha_mm)
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(cloud, alpha)
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) == 0:
        raise InvalidMeshError(f"{name}: {method} built no surface from {len(points)} points")
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels, counts = np.asarray(labels), np.asarray(counts)
    small = counts < MIN_PIECE * counts.max()
    if small.any():  # floating specks; real parts cut apart by trimming (a glass's foot) are kept
        mesh.remove_triangles_by_mask(small[labels])
        mesh.remove_unreferenced_vertices()
    if max_triangles is not None and len(mesh.triangles) > max_triangles:
        mesh = mesh.simplify_quadric_decimation(int(max_triangles))
        mesh.remove_degenerate_triangles()
        mesh.remove_unreferenced_vertices()
    if method == "poisson" and not mesh.is_edge_manifold():
        # Marching cubes and decimation leave an edge with four faces here and there: drop those faces and
        # close the few-edge holes they leave.
        mesh.remove_non_manifold_edges()
        mesh.remove_unreferenced_vertices()
        return _close_small_holes(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles))
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def _close_small_holes(
    vertices: np.ndarray, triangles: np.ndarray, max_edges: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Close each hole of at most ``max_edges`` boundary edges with a fan around its centroid (a new
    vertex), wound like the faces beside it."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    triangles = np.asarray(triangles, dtype=np.int64)
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    keys = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
    if not len(border):
        return vertices, triangles
    n = len(vertices)
    graph = coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(n, n))
    _, hole = connected_components(graph, directed=False)
    hole = hole[border[:, 0]]
    ids, size = np.unique(hole, return_counts=True)
    small = ids[size <= max_edges]
    pick = np.isin(hole, small)
    border, hole = border[pick], hole[pick]
    if not len(border):
        return vertices, triangles
    index = {h: n + i for i, h in enumerate(small)}
    centres = np.array([vertices[border[hole == h, 0]].mean(axis=0) for h in small])
    fan = np.stack([border[:, 1], border[:, 0], np.array([index[h] for h in hole])], axis=1)
    return np.concatenate([vertices, centres]), np.concatenate([triangles, fan])


def _to_model(vertices, triangles, *, name, label, size_mm, source, pre_transform=None) -> ObjectModel:
    from perception.orientation import orient_outward

    where = source or name
    vertices, triangles = meshio.validate_arrays(vertices, triangles, where)
    vertices, triangles, _ = meshio.repair(vertices, triangles, None, where)
    # Poisson from outward normals is outward already; ball pivoting and alpha shapes may wind either way.
    triangles, _ = orient_outward(vertices, triangles, where)
    transform = np.eye(4) if pre_transform is None else pre_transform
    if size_mm is not None:
        vertices, scale = normalize(vertices, size_mm)
        transform = scale @ transform
    return ObjectModel(vertices, triangles.astype(np.int32), name=name, label=label, transform=transform, source=source)


def points_to_model(
    points: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    name: str = "point cloud",
    label: str | None = None,
    size_mm: float | None = DEFAULT_SIZE_MM,
    method: str = "poisson",
    poisson_depth: int = 8,
    density_trim: float | None = 1.0,
    max_triangles: int | None = 20000,
    outlier_neighbors: int = 20,
    outlier_std: float = 2.5,
    normal_neighbors: int = 20,
    viewpoints: np.ndarray | None = None,
    source: str | None = None,
    alpha_mm: float | None = None,
    seed: int = 0,
) -> ObjectModel:
    """Points (mm) -> validated -> outliers removed -> oriented normals -> surface -> ``ObjectModel``.

    Given normals are kept (re-oriented towards ``viewpoints`` if those are given); otherwise they are
    estimated (:func:`estimate_normals`). ``size_mm=None`` keeps the cloud's own scale and position.

    Raises:
        InvalidMeshError: a bad cloud (:func:`validate_points`), bad normals, or no surface.
        InvalidArgumentError: unknown surface method or bad parameter.
    """
    where = source or name  # messages name the file when there is one
    points = validate_points(points, where)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        norm = np.linalg.norm(normals, axis=1, keepdims=True) if normals.shape == points.shape else None
        if norm is None or not np.isfinite(normals).all() or (norm == 0).any():
            raise InvalidMeshError(f"{where}: normals must be finite, non-zero and shaped like the points {points.shape}")
        normals = normals / norm
    if viewpoints is not None and np.ndim(viewpoints) == 2:
        points, normals, viewpoints = _clean(points, normals, viewpoints, outlier_neighbors, outlier_std)
    else:
        points, normals, _ = _clean(points, normals, None, outlier_neighbors, outlier_std)
    points = validate_points(points, f"{where} (after outlier removal)")
    if normals is None:
        normals = estimate_normals(points, k=normal_neighbors, viewpoints=viewpoints, seed=seed)
    elif viewpoints is not None:
        to_view = np.broadcast_to(viewpoints, points.shape) - points
        normals = np.where(((normals * to_view).sum(axis=1) < 0)[:, None], -normals, normals)
    vertices, triangles = surface_from_points(
        points, normals, method=method, poisson_depth=poisson_depth, density_trim=density_trim,
        max_triangles=max_triangles, alpha_mm=alpha_mm, name=where,
    )
    return _to_model(vertices, triangles, name=name, label=label, size_mm=size_mm, source=source)


def load_points(
    source: str | Path | o3d.geometry.PointCloud | np.ndarray,
    *,
    label: str | None = None,
    name: str | None = None,
    size_mm: float | None = DEFAULT_SIZE_MM,
    method: str = "poisson",
    poisson_depth: int = 8,
    density_trim: float | None = 1.0,
    use_file_normals: bool = True,
    **kwargs,
) -> ObjectModel:
    """Load a point cloud (file, ``open3d.geometry.PointCloud`` or (N, 3) array, mm) as an ``ObjectModel``.

    The sibling of :func:`perception.geometry.load_object` for clouds: see :func:`points_to_model` for the
    steps and the remaining keyword arguments. Like ``load_object`` it centres and scales to a bounding-box
    diagonal of ``size_mm`` (``None`` keeps the cloud's coordinates); ``transform`` maps cloud to model.

    Raises:
        MeshLoadError: missing, empty, unknown type, or unparseable file.
        InvalidMeshError: empty cloud, NaN/Inf, a handful of points, collinear or coplanar points, or no
            surface could be built.
        InvalidArgumentError: unknown surface method or bad parameter.
    """
    normals = None
    src = None
    if isinstance(source, o3d.geometry.PointCloud):
        name = name or "open3d-pointcloud"
        points = np.asarray(source.points, dtype=np.float64)
        normals = np.asarray(source.normals, dtype=np.float64) if source.has_normals() else None
    elif isinstance(source, np.ndarray):
        name = name or "points"
        points = source
    else:
        path = Path(source)
        name = name or path.stem
        src = str(path)
        points, normals, _ = read_points(path)
    if not use_file_normals:
        normals = None
    return points_to_model(
        points, normals, name=name, label=label, size_mm=size_mm, method=method,
        poisson_depth=poisson_depth, density_trim=density_trim, source=src, **kwargs,
    )


# ------------------------------------------------------------------------------------ RGB-D scenes
@dataclass
class Cluster:
    """One object segmented from a tabletop scene.

    Attributes:
        points: (N, 3) world points, mm.
        colors: (N, 3) RGB in [0, 1].
        viewpoints: (N, 3) camera centre each point was seen from, mm.
        centroid: (3,) mean of the (visible) points, mm.
        center: (3,) centre of the prism the cluster stands in: the centroid's foot on the table raised
            by half the height, mm (a camera sees the top and front only; this estimates the object's centre).
        height_mm: largest height above the table plane, mm.
    """

    points: np.ndarray
    colors: np.ndarray
    viewpoints: np.ndarray
    centroid: np.ndarray
    center: np.ndarray
    height_mm: float


@dataclass
class TableScene:
    """A segmented tabletop: the table plane and the object clusters on it, largest first.

    Attributes:
        plane: (4,) a, b, c, d with unit normal (a, b, c) pointing up (towards the cameras): a x + b y + c z + d = 0.
        n_table_points: inliers of the plane.
        clusters: the objects, largest first.
        points, colors, labels: the points after down-sampling (mm), their RGB in [0, 1] and their labels
            (-2 table, -1 noise or off the table, k cluster k).
        floor_mm: the table's own noise: points lower than this above the plane cannot be told from it
            (three robust standard deviations of the inliers' heights, at most the plane tolerance), mm.
    """

    plane: np.ndarray
    n_table_points: int
    clusters: list[Cluster] = field(default_factory=list)
    points: np.ndarray | None = None
    colors: np.ndarray | None = None
    labels: np.ndarray | None = None
    floor_mm: float = 0.0


def frames_to_points(frames, *, max_depth_mm: float = 1500.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (mm), colours and viewpoints of all valid pixels of ``frames`` (depth <= ``max_depth_mm``).

    Raises:
        InvalidMeshError: no frame has any depth.
    """
    pts, cols, views = [], [], []
    for frame in frames:
        p, c = frame.points(frame.valid & (frame.depth_mm <= max_depth_mm))
        pts.append(p)
        cols.append(c)
        views.append(np.broadcast_to(frame.camera_position, p.shape))
    if not pts or sum(len(p) for p in pts) == 0:
        raise InvalidMeshError(f"{frames[0].name if frames else 'frames'}: no valid depth in the capture")
    return np.concatenate(pts), np.concatenate(cols), np.concatenate(views)


def segment_table(
    points: np.ndarray,
    colors: np.ndarray | None = None,
    viewpoints: np.ndarray | None = None,
    *,
    voxel_mm: float = 3.0,
    plane_tolerance_mm: float = 6.0,
    cluster_eps_mm: float = 8.0,
    min_cluster_points: int = 100,
    max_height_mm: float = 400.0,
    up_hint: np.ndarray | None = None,
    method: str = "euclidean",
    smooth_deg: float = 30.0,
    color_tolerance: float = 0.1,
    seed: int = 0,
) -> TableScene:
    """Find the table plane (RANSAC) and cluster what stands on it (DBSCAN), all in mm.

    The cloud is down-sampled on a ``voxel_mm`` grid; the plane with the most inliers within
    ``plane_tolerance_mm`` is the table, refined by least squares on its inliers; its normal points
    towards ``up_hint`` (default: the mean viewpoint, or -y in camera coordinates, i.e. image up). Points
    more than ``plane_tolerance_mm`` and at most ``max_height_mm`` above it are clustered with DBSCAN
    (``cluster_eps_mm``); clusters under ``min_cluster_points`` are dropped. Each cluster then grows down
    into the points between the table's noise floor (:attr:`TableScene.floor_mm`) and
    ``plane_tolerance_mm`` that join it within ``cluster_eps_mm`` and lie under its footprint: the lowest
    millimetres of an object (a glass's foot, the base of a wall) are not table.

    ``method="euclidean"`` clusters by distance alone (DBSCAN), right for one object or objects apart.
    ``method="smooth"`` separates objects that touch: neighbours (within ``cluster_eps_mm``) are joined
    only where their normals differ by less than ``smooth_deg`` and their colours by less than
    ``color_tolerance`` (max over RGB in [0, 1]); a region-growing segmentation (as PCL's
    ``RegionGrowingRGB``) that may split one object with sharp creases or strong print into several.

    Raises:
        InvalidMeshError: too few points, or no plane found.
        InvalidArgumentError: an unknown method.
    """
    if method not in ("euclidean", "smooth"):
        raise InvalidArgumentError(f"scene: unknown segmentation method {method!r} (euclidean or smooth)")
    points = _as_points(points, "scene")
    if len(points) < 3 * MIN_POINTS:
        raise InvalidMeshError(f"scene: only {len(points)} points with depth; cannot find a table")
    colors = np.zeros_like(points) if colors is None else np.asarray(colors, dtype=np.float64)
    viewpoints = np.zeros_like(points) if viewpoints is None else np.asarray(viewpoints, dtype=np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    # Carry colour and viewpoint through the voxel average: colours as colours, viewpoints as normals.
    cloud.colors = o3d.utility.Vector3dVector(colors)
    cloud.normals = o3d.utility.Vector3dVector(viewpoints)
    if voxel_mm > 0:
        cloud = cloud.voxel_down_sample(voxel_mm)
    pts = np.asarray(cloud.points).copy()
    cols = np.asarray(cloud.colors).copy()
    views = np.asarray(cloud.normals).copy()
    o3d.utility.random.seed(int(seed))
    cloud.normals = o3d.utility.Vector3dVector()
    _, inliers = cloud.segment_plane(plane_tolerance_mm, 3, 1000)
    inliers = np.asarray(inliers, dtype=np.int64)
    if len(inliers) < 3:
        raise InvalidMeshError("scene: no table plane found")
    # Least-squares refinement on the inliers, twice, re-selecting them: Open3D's RANSAC runs on several
    # threads and may return another of equally good candidates under load; the refit plane does not.
    for _ in range(2):
        centre = pts[inliers].mean(axis=0)
        normal = np.linalg.svd(pts[inliers] - centre, full_matrices=False)[2][2]
        inliers = np.nonzero(np.abs((pts - centre) @ normal) <= plane_tolerance_mm)[0]
    up = np.asarray(up_hint, dtype=np.float64) if up_hint is not None else views.mean(axis=0) - centre
    if np.linalg.norm(up) < 1e-9:
        up = np.array([0.0, -1.0, 0.0])
    if normal @ up < 0:
        normal = -normal
    plane = np.r_[normal, -normal @ centre]
    height = pts @ normal + plane[3]
    # The table's noise, robustly (MAD): above 3 sigma a point stands out of the plane.
    floor = min(plane_tolerance_mm, 3 * 1.4826 * float(np.median(np.abs(height[inliers]))))
    labels = np.full(len(pts), -1, dtype=np.int64)
    on_table = np.abs(height) <= plane_tolerance_mm
    labels[on_table] = -2
    above = (height > plane_tolerance_mm) & (height <= max_height_mm)
    above = np.nonzero(above)[0]
    if on_table.sum() >= 3 and len(above):
        # Objects *on* the table: above it and inside the convex hull of its inliers, seen from above
        # (the polygonal prism of PCL's tabletop segmentation); drops walls, robots and people beside it.
        above = above[_inside_table(pts[above], pts[on_table], normal)]
    clusters: list[Cluster] = []
    if len(above):
        if method == "smooth":
            raw = _smooth_components(
                pts[above], cols[above], views[above], cluster_eps_mm, smooth_deg, color_tolerance
            )
        else:
            sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[above]))
            raw = np.asarray(sub.cluster_dbscan(cluster_eps_mm, 10), dtype=np.int64)
        found = []
        for k in range(raw.max(initial=-1) + 1):
            idx = above[raw == k]
            if len(idx) >= min_cluster_points:
                found.append(idx)
        # Order by size, then by first index: independent of DBSCAN's label numbering.
        found.sort(key=lambda idx: (-len(idx), int(idx[0])))
        low = np.nonzero(on_table & (height > floor))[0]
        if len(low):
            low = low[_inside_table(pts[low], pts[on_table], normal)]
        taken = np.zeros(len(low), dtype=bool)
        for k, idx in enumerate(found):
            grown = _grow_down(pts, idx, low, taken, cluster_eps_mm, normal)
            idx = found[k] = np.sort(np.concatenate([idx, grown]))
            labels[idx] = k
            top = float(height[idx].max())
            mean = pts[idx].mean(axis=0)
            # Prism centre: the mean's foot on the table, raised by half the height.
            center = mean - (height[idx].mean() - 0.5 * top) * normal
            clusters.append(Cluster(pts[idx], cols[idx], views[idx], mean, center, top))
    log.info("scene: table %d points (floor %.1f mm), %d clusters", int(on_table.sum()), floor, len(clusters))
    return TableScene(plane, int(on_table.sum()), clusters, pts, cols, labels, floor)


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes (u, v) spanning the plane with unit ``normal``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _grow_down(
    pts: np.ndarray, idx: np.ndarray, low: np.ndarray, taken: np.ndarray, eps: float, normal: np.ndarray
) -> np.ndarray:
    """The points ``low`` (indices into ``pts``, not yet ``taken``) reachable from cluster ``idx`` in steps
    of at most ``eps`` mm, each within ``eps`` of the cluster's footprint (the convex hull of its points
    seen from above the table: growth cannot creep along the table). Marks them in ``taken``."""
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    if not len(low):
        return low
    u, v = _plane_axes(normal)
    flat = lambda p: np.stack([p @ u, p @ v], axis=1)
    try:
        hull = ConvexHull(flat(pts[idx])).equations
    except (QhullError, ValueError):
        return low[:0]
    allowed = np.all(flat(pts[low]) @ hull[:, :2].T + hull[:, 2] <= eps, axis=1) & ~taken
    tree = cKDTree(pts[low])
    frontier = pts[idx]
    grown = np.zeros(len(low), dtype=bool)
    while len(frontier):
        hits = tree.query_ball_point(frontier, eps)
        hits = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))
        new = hits[allowed[hits] & ~grown[hits]]
        grown[new] = True
        frontier = pts[low[new]]
    taken |= grown
    return low[grown]


def _smooth_components(
    pts: np.ndarray, cols: np.ndarray, views: np.ndarray, eps: float, smooth_deg: float, color_tol: float
) -> np.ndarray:
    """Connected components of the neighbour graph whose edges join smooth, similarly coloured points."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    normals = estimate_normals(pts, k=20, viewpoints=views)
    pairs = cKDTree(pts).query_pairs(eps, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    keep = ((normals[i] * normals[j]).sum(axis=1) > np.cos(np.radians(smooth_deg))) & (
        np.abs(cols[i] - cols[j]).max(axis=1) < color_tol
    )
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(len(pts), len(pts)))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _inside_table(pts: np.ndarray, table: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """True where a point's projection on the table plane falls inside the convex hull of the table points."""
    from scipy.spatial import ConvexHull, QhullError

    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    flat = lambda p: np.stack([p @ u, p @ v], axis=1)
    try:
        equations = ConvexHull(flat(table)).equations  # outward half-planes a . p + b <= 0 inside
    except (QhullError, ValueError):  # a degenerate table outline: keep everything
        return np.ones(len(pts), dtype=bool)
    return np.all(flat(pts) @ equations[:, :2].T + equations[:, 2] <= 1e-9, axis=1)


def merge_stacked(scene: TableScene, cluster: Cluster) -> Cluster:
    """``cluster`` joined with every other cluster of ``scene`` whose footprint centre (its centroid seen
    from above the table) lies inside ``cluster``'s footprint, or the other way round.

    On a table objects stand side by side, not on top of each other, so pieces stacked above one
    footprint are one object split where the camera saw too little of it (a wine glass's thin stem
    leaves its bowl and foot apart).
    """
    from scipy.spatial import ConvexHull, QhullError

    normal = scene.plane[:3]
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)

    def footprint(c: Cluster):
        flat = np.stack([c.points @ u, c.points @ v], axis=1)
        try:
            return ConvexHull(flat).equations, flat.mean(axis=0)
        except (QhullError, ValueError):
            return None, flat.mean(axis=0)

    def inside(equations, point) -> bool:
        return equations is not None and bool(np.all(equations[:, :2] @ point + equations[:, 2] <= 0))

    hull, centre = footprint(cluster)
    parts = [cluster]
    for other in scene.clusters:
        if other is cluster:
            continue
        other_hull, other_centre = footprint(other)
        if inside(hull, other_centre) or inside(other_hull, centre):
            parts.append(other)
    if len(parts) == 1:
        return cluster
    points = np.concatenate([c.points for c in parts])
    height = points @ normal + scene.plane[3]
    top = float(height.max())
    mean = points.mean(axis=0)
    return Cluster(
        points, np.concatenate([c.colors for c in parts]), np.concatenate([c.viewpoints for c in parts]), mean,
        mean - (height.mean() - 0.5 * top) * normal, top,
    )


def pick_cluster(scene: TableScene, target: np.ndarray | None = None) -> Cluster:
    """The cluster whose centroid is nearest ``target`` (mm), or the largest one.

    Raises:
        InvalidMeshError: the scene has no clusters.
    """
    if not scene.clusters:
        raise InvalidMeshError("scene: no object found on the table (no cluster above the plane)")
    if target is None:
        return scene.clusters[0]
    d = [np.linalg.norm(c.centroid - target) for c in scene.clusters]
    return scene.clusters[int(np.argmin(d))]


def refine_views(
    clouds: list[np.ndarray], *, max_distance_mm: float = 2.0, max_rotation_deg: float = 2.0
) -> list[np.ndarray]:
    """ICP-refine each view's points (already aligned by known poses, world mm) onto the union of the
    previous ones; returns the 4 x 4 corrections (identity for the first view).

    Point-to-plane ICP (Open3D) with correspondences within ``max_distance_mm``: on virtual OAK captures
    with exact poses it stays within 0.2 mm of the identity, where point-to-point ICP within 5 mm drifted
    by 1-1.5 mm and tripled the surface error (``benchmarks/reconstruction.py``). Corrections larger than
    ``max_distance_mm`` or ``max_rotation_deg`` are refused (identity): poses are known, ICP only polishes.
    """
    if not clouds:
        return []
    reg = o3d.pipelines.registration
    corrections = [np.eye(4)]
    reference = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clouds[0]))
    for i, pts in enumerate(clouds[1:], start=1):
        moving = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        reference.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        result = reg.registration_icp(
            moving, reference, max_distance_mm, np.eye(4), reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=30),
        )
        t = np.asarray(result.transformation)
        angle = np.degrees(np.arccos(np.clip((np.trace(t[:3, :3]) - 1) / 2, -1.0, 1.0)))
        if result.fitness < 0.05 or np.linalg.norm(t[:3, 3]) > max_distance_mm or angle > max_rotation_deg:
            log.info("view %d: ICP correction refused (fitness %.2f, %.2f mm, %.2f deg)", i, result.fitness,
                     np.linalg.norm(t[:3, 3]), angle)
            t = np.eye(4)
        # Open3D sums over threads in no fixed order: the last bits of t vary from run to run.
        t = np.round(t, 9)
        corrections.append(t)
        reference.points.extend(o3d.utility.Vector3dVector(pts @ t[:3, :3].T + t[:3, 3]))
    return corrections


def _fill_row_gaps(depth: np.ndarray, max_gap: int, keep: int = 2) -> np.ndarray:
    """Depth with each gap of at most ``max_gap`` pixels along a row (the stereo baseline) filled with the
    farther of its two ends: stereo occlusion leaves such gaps beside every near edge, and what the
    occluded pixels see is the background continuing behind it (the fill of semi-global matching). The
    ``keep`` pixels next to either end stay empty: there the edge itself was dropped, which may be near."""
    width = depth.shape[1]
    valid = depth > 0
    cols = np.broadcast_to(np.arange(width), depth.shape)
    left = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    right = np.fliplr(np.minimum.accumulate(np.fliplr(np.where(valid, cols, width)), axis=1))
    fill = ~valid & (left >= 0) & (right < width) & (right - left - 1 <= max_gap)
    fill &= (cols - left > keep) & (right - cols > keep)
    r = np.nonzero(fill)[0]
    out = depth.copy()
    out[fill] = np.maximum(depth[r, left[fill]], depth[r, right[fill]])
    return out


@dataclass
class Carving:
    """The space RGB-D frames leave for an object on a table (:func:`carve`): voxels no ray showed empty.

    Attributes:
        solid: (I, J, K) bool, the voxels kept: the object and whatever no camera saw.
        origin: (3,) the grid's corner in table coordinates (along ``axes[0]``, ``axes[1]``, height), mm.
        axes: (3, 3) rows: two unit axes in the table plane and its upward unit normal.
        offset: the plane's d (height of a point p is ``p @ axes[2] + offset``), mm.
        voxel_mm: the voxel side, mm.
    """

    solid: np.ndarray
    origin: np.ndarray
    axes: np.ndarray
    offset: float
    voxel_mm: float

    def _local(self, points: np.ndarray) -> np.ndarray:
        return points @ self.axes.T + np.array([0.0, 0.0, self.offset])

    def _world(self, local: np.ndarray) -> np.ndarray:
        return (local - np.array([0.0, 0.0, self.offset])) @ self.axes

    def contains(self, points: np.ndarray, dilation: int = 0) -> np.ndarray:
        """(N,) True where a point lies in a solid voxel, the solid grown by ``dilation`` voxels first."""
        from scipy import ndimage

        solid = np.pad(self.solid, dilation)
        if dilation:
            solid = ndimage.binary_dilation(solid, iterations=dilation)
        ijk = np.floor((self._local(points) - self.origin) / self.voxel_mm).astype(np.int64) + dilation
        inside = np.all((ijk >= 0) & (ijk < np.array(solid.shape)), axis=1)
        out = np.zeros(len(points), dtype=bool)
        out[inside] = solid[tuple(ijk[inside].T)]
        return out

    def boundary(
        self, points: np.ndarray | None = None, normals: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Centres (M, 3) and outward unit normals (M, 3) of the solid's faces that border empty space, mm.

        With observed ``points`` and their outward unit ``normals``, the faces where the surface was seen
        are left out: those within 1.75 voxels of an observed point and not behind its tangent plane (by
        half a voxel; the far side of a thin wall stays). The rest is where the surface must close unseen.
        """
        from scipy.spatial import cKDTree

        s = self.voxel_mm
        padded = np.pad(self.solid, 1)
        faces, outward = [], []
        for axis in range(3):
            for step in (-1, 1):
                beside = np.roll(padded, -step, axis=axis)[1:-1, 1:-1, 1:-1]
                ijk = np.argwhere(self.solid & ~beside)
                direction = np.zeros(3)
                direction[axis] = step
                faces.append(self._world(self.origin + (ijk + 0.5 + 0.5 * direction) * s))
                outward.append(np.broadcast_to(direction @ self.axes, (len(ijk), 3)))
        faces, outward = np.concatenate(faces), np.concatenate(outward)
        if points is None or not len(points) or not len(faces):
            return faces, outward
        dist, near = cKDTree(points).query(faces, k=8, distance_upper_bound=1.75 * s)
        found = np.isfinite(dist)
        near = np.where(found, near, 0)
        ahead = np.einsum("mkd,mkd->mk", faces[:, None, :] - points[near], normals[near]) > -0.5 * s
        keep = ~np.any(found & ahead, axis=1)
        return faces[keep], outward[keep]


def carve(
    frames,
    plane: np.ndarray,
    points: np.ndarray,
    *,
    voxel_mm: float = 2.0,
    table_mm: float = 2.0,
    margin_mm: float | None = None,
    max_gap_px: int = 48,
) -> Carving:
    """Space carving around an object's ``points`` (world mm) standing on the table ``plane``.

    A ``voxel_mm`` grid covers the points (``margin_mm`` around them, default two voxels; its layers
    below the plane are empty). A voxel is empty if some frame's ray passes through it to a surface more than half a voxel
    further on, or to the table (a measured pixel whose point lies within ``table_mm`` of the plane, or
    below it); below the plane all is empty. Gaps in a depth row up to ``max_gap_px`` wide count as the
    farther of their ends (:func:`_fill_row_gaps`). What stays is the object together with what the
    cameras could not see: where it rests on the table, the inside of a mug below the sight lines, the
    back of a one-view capture; solid pieces that hold no observed point (specks no ray reached) go.
    """
    from scipy import ndimage

    normal = np.asarray(plane[:3], dtype=np.float64)
    s = float(voxel_mm)
    margin = 2 * s if margin_mm is None else float(margin_mm)
    u, v = _plane_axes(normal)
    empty = Carving(np.zeros((0, 0, 0), dtype=bool), np.zeros(3), np.stack([u, v, normal]), float(plane[3]), s)
    local = empty._local(points)
    lo, hi = local.min(axis=0) - margin, local.max(axis=0) + margin
    lo[2] = -s * np.ceil(margin / s)  # a few layers below the table: empty, so the bottom is a boundary
    shape = tuple(int(n) for n in np.ceil((hi - lo) / s).astype(int))
    grid = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1).reshape(-1, 3)
    centres = lo + (grid + 0.5) * s
    world = empty._world(centres)
    free = centres[:, 2] < 0
    for frame in frames:
        k, rot, eye = frame.intrinsics, frame.pose[:3, :3], frame.pose[:3, 3]
        cam = (world - eye) @ rot
        z = cam[:, 2]
        front = z > 0
        col = np.full(len(z), -1)
        row = np.full(len(z), -1)
        col[front] = np.rint(k.fx * cam[front, 0] / z[front] + k.cx)
        row[front] = np.rint(k.fy * cam[front, 1] / z[front] + k.cy)
        ok = front & (col >= 0) & (col < k.width) & (row >= 0) & (row < k.height)
        depth = np.zeros(len(z))
        depth[ok] = _fill_row_gaps(frame.depth_mm, max_gap_px)[row[ok], col[ok]]
        measured = np.zeros(len(z), dtype=bool)
        measured[ok] = frame.depth_mm[row[ok], col[ok]] > 0
        ok &= depth > 0
        hit = (cam[ok] * (depth[ok] / z[ok])[:, None]) @ rot.T + eye  # the point this pixel saw
        on_table = measured[ok] & (hit @ normal + plane[3] <= table_mm)
        free[np.nonzero(ok)[0]] |= on_table | (z[ok] < depth[ok] - 0.5 * s)
    solid = ~free.reshape(shape)
    pieces, _ = ndimage.label(solid)
    cells = np.clip(np.floor((local - lo) / s).astype(int), 0, np.array(shape) - 1)
    held = np.unique(pieces[tuple(cells.T)])
    return Carving(np.isin(pieces, held[held > 0]), lo, empty.axes, empty.offset, s)


@dataclass
class Reconstruction:
    """What :func:`reconstruct_frames` built: the model and the intermediate data (for figures and checks).

    Attributes:
        model: the reconstructed object, in world mm unless ``size_mm`` was given.
        points, normals: (N, 3) the fused object points and their oriented normals, world mm.
        scenes: the segmented scene of each frame.
        corrections: the ICP correction (4 x 4) applied to each view.
        support: (M, 3) the points added where no camera saw the surface (:meth:`Carving.boundary`), mm.
    """

    model: ObjectModel
    points: np.ndarray
    normals: np.ndarray
    scenes: list[TableScene]
    corrections: list[np.ndarray]
    support: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def reconstruct_frames(
    frames,
    *,
    target: np.ndarray | None = None,
    name: str = "capture",
    label: str | None = None,
    size_mm: float | None = None,
    icp: bool = True,
    voxel_mm: float = 2.0,
    poisson_depth: int = 7,
    density_trim: float | None = None,
    max_depth_mm: float = 1500.0,
    roi_mm: float | None = 400.0,
    cluster_eps_mm: float = 8.0,
    method: str = "euclidean",
    close: bool = True,
    seed: int = 0,
    **surface_kwargs,
) -> Reconstruction:
    """RGB-D frames of one object on a table (poses in ``frame.pose``) -> a reconstructed ``ObjectModel``.

    Per frame: points in the world frame, table removed, the cluster nearest ``target`` (world mm;
    default: the first frame's largest cluster, then the nearest to it) kept, with the pieces stacked
    above its footprint (:func:`merge_stacked`). Normals are estimated in each view and turned towards its
    camera, the views ICP-refined onto each other, outliers removed, and a Poisson surface
    (``poisson_depth``) built; ``size_mm=None`` keeps world millimetres, else the model is scaled like
    ``load_object``'s.

    ``close``: the surface is closed where no camera saw it, as the object is: the faces of the space
    the frames left uncarved (:func:`carve`) that no observed point explains (the bottom on the table,
    the inside of a mug below the sight lines) join the points (:attr:`Reconstruction.support`). Should
    Poisson still leak (a thin shell, a spoon, whose two sides lie within a few Poisson cells: phantom
    sheets outside the carved space), the surface is built from the faces of the carved space alone,
    closed by construction and a voxel coarser. ``close=False`` keeps the seen points alone; pass
    ``density_trim=1.0`` then to cut away Poisson's extrapolation (an open surface, as before).
    ``method`` is the segmentation of :func:`segment_table` (``"smooth"`` for cluttered real scenes).
    With a ``target``, only points within ``roi_mm`` of it are segmented (speed; ``None``: all).

    Raises:
        InvalidMeshError: no depth, no table, no object, or no surface.
    """
    frames = list(frames)
    if not frames:
        raise InvalidMeshError(f"{name}: no frames to reconstruct from")
    scenes, picked = [], []
    for i, frame in enumerate(frames):
        pts, cols, views = frames_to_points([frame], max_depth_mm=max_depth_mm)
        if target is not None and roi_mm is not None:  # only the neighbourhood of the object matters
            near = np.linalg.norm(pts - target, axis=1) <= roi_mm
            if near.sum() >= 3 * MIN_POINTS:
                pts, cols, views = pts[near], cols[near], views[near]
        scene = segment_table(
            pts, cols, views, voxel_mm=voxel_mm, cluster_eps_mm=cluster_eps_mm, method=method, seed=seed + i
        )
        cluster = merge_stacked(scene, pick_cluster(scene, target))
        if target is None:
            target = cluster.centroid
        scenes.append(scene)
        picked.append(cluster)
    clouds = [c.points for c in picked]
    corrections = refine_views(clouds) if icp and len(clouds) > 1 else [np.eye(4)] * len(clouds)
    points = np.concatenate([p @ t[:3, :3].T + t[:3, 3] for p, t in zip(clouds, corrections)])
    # Normals per view, then fused: one view sees one side of a thin wall, the fused cloud both sides
    # within a few millimetres, where a shared neighbourhood would mix them.
    normals = np.concatenate(
        [estimate_normals(c.points, viewpoints=c.viewpoints) @ t[:3, :3].T for c, t in zip(picked, corrections)]
    )
    support, outward = np.zeros((0, 3)), np.zeros((0, 3))
    build = lambda pts, nrm: points_to_model(
        pts, nrm, name=name, label=label, size_mm=None, poisson_depth=poisson_depth, density_trim=density_trim,
        seed=seed, **surface_kwargs,
    )
    if close:
        carving = carve(frames, scenes[0].plane, points, voxel_mm=max(voxel_mm, 1.0),
                        table_mm=max(s.floor_mm for s in scenes))
        support, outward = carving.boundary(points, normals)
        model = build(np.concatenate([points, support]), np.concatenate([normals, outward]))
        outside = ~carving.contains(model.vertices, dilation=2)
        if not model.is_watertight or outside.mean() > LEAK_FRACTION:
            log.info("%s: Poisson leaked (%.1f %% of the surface outside the carved space); surface of the "
                     "carved space instead", name, 100 * outside.mean())
            support, outward = carving.boundary()
            model = build(support, outward)
        # Nothing of the object lies below the table: a Poisson sheet that does is pressed onto it.
        plane = scenes[0].plane
        height = model.vertices @ plane[:3] + plane[3]
        if (height < 0).any():
            vertices = model.vertices - np.minimum(height, 0.0)[:, None] * plane[:3]
            model = ObjectModel(vertices, model.triangles, name=name, label=label)
    else:
        model = build(points, normals)
    if size_mm is not None:
        vertices, scale = normalize(model.vertices, size_mm)
        model = ObjectModel(vertices, model.triangles, name=name, label=label, transform=scale)
    return Reconstruction(model, points, normals, scenes, corrections, support)


def _sample_surface(model: ObjectModel, n: int, rng: np.random.Generator) -> np.ndarray:
    areas = model.triangle_areas
    if areas.sum() <= 0:
        raise InvalidMeshError(f"{model.name}: zero surface area")
    tri = rng.choice(model.n_triangles, n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = (model.vertices[model.triangles[tri, i]] for i in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def surface_error(model: ObjectModel, truth: ObjectModel, *, n_samples: int = 20000, seed: int = 0) -> dict:
    """How far a reconstruction lies from the true surface, mm.

    Accuracy: ``n_samples`` points drawn uniformly (area-weighted, seeded) on ``model``, each one's
    distance to ``truth``: ``mean_mm``, ``p95_mm``, ``max_mm``. Completeness: the same from points on
    ``truth`` to ``model`` (``coverage_mean_mm``, ``coverage_p95_mm``); parts no camera saw (the bottom
    on the table) count here.

    Raises:
        InvalidMeshError: a mesh with zero area.
    """
    rng = np.random.default_rng(seed)
    _, dist = truth.closest_points(_sample_surface(model, n_samples, rng))
    _, back = model.closest_points(_sample_surface(truth, n_samples, rng))
    return {
        "mean_mm": float(dist.mean()),
        "p95_mm": float(np.quantile(dist, 0.95)),
        "max_mm": float(dist.max()),
        "coverage_mean_mm": float(back.mean()),
        "coverage_p95_mm": float(np.quantile(back, 0.95)),
    }


__all__ = [
    "METHODS",
    "POINT_SUFFIXES",
    "Cluster",
    "Reconstruction",
    "TableScene",
    "estimate_normals",
    "frames_to_points",
    "load_points",
    "merge_stacked",
    "pick_cluster",
    "points_to_model",
    "read_points",
    "reconstruct_frames",
    "refine_views",
    "segment_table",
    "surface_error",
    "validate_points",
    "write_points",
]
