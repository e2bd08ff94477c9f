"""Reading, validating and repairing mesh files (OFF, OBJ, PLY, STL).

Why not hand everything to Open3D: its ``read_triangle_mesh`` never raises on a bad file (it returns an
empty or partial mesh and accepts out-of-range indices), and pymeshlab can take the whole process down on
a malformed file. So OFF (including ModelNet's glued ``OFF216 183 0`` header and polygon faces) is parsed
here, the other formats go through Open3D and are validated afterwards, header counts are checked against
the file size before anything is allocated, and pymeshlab only ever sees arrays validated here.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception.errors import InvalidMeshError, MeshLoadError

log = logging.getLogger(__name__)

MESH_SUFFIXES = frozenset({".off", ".obj", ".ply", ".stl"})

# Smallest possible bytes of an ASCII OFF vertex line ("0 0 0\n") and triangle line ("3 0 1 2\n").
_MIN_OFF_VERTEX_BYTES = 6
_MIN_OFF_FACE_BYTES = 8


@dataclass
class RawMesh:
    """Arrays as read from a file, before validation: vertices (V, 3), triangles (F, 3), colours or None."""

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None = None


def check_file(path: str | Path, kind: str, suffixes) -> tuple[Path, str]:
    """``path`` as a Path and its lower-case suffix, after checking it names a non-empty file of a known type.

    Raises:
        MeshLoadError: missing, a directory, an unknown suffix, or empty; the message names ``kind``.
    """
    path = Path(path)
    if not path.exists():
        raise MeshLoadError(f"{path}: no such file")
    if path.is_dir():
        raise MeshLoadError(f"{path}: is a directory, not a {kind} file")
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        raise MeshLoadError(f"{path}: unknown {kind} type {suffix!r} (expected one of {sorted(suffixes)})")
    if path.stat().st_size == 0:
        raise MeshLoadError(f"{path}: file is empty")
    return path, suffix


def read_mesh(path: Path) -> RawMesh:
    """Read a mesh file into arrays; polygon faces are fan-triangulated.

    Raises:
        MeshLoadError: missing file, directory, unknown suffix, or a file that cannot be parsed.
    """
    path, suffix = check_file(path, "mesh", MESH_SUFFIXES)
    if suffix == ".off":
        return read_off(path)
    _check_header_counts(path, suffix)
    return _read_open3d(path)


def read_off(path: Path) -> RawMesh:
    """Parse an ASCII OFF file (``OFF``/``COFF``, glued ``OFFv f e`` headers, comments, polygon faces)."""
    data = path.read_bytes()
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        raise MeshLoadError(f"{path}: not an ASCII OFF file (binary or corrupt content)") from None
    # Drop comments, split into tokens; the header keyword may be glued to the counts ("OFF216 183 0").
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise MeshLoadError(f"{path}: OFF file has no content")
    match = re.fullmatch(r"(C?N?OFF)\s*(.*)", lines[0])
    if not match:
        raise MeshLoadError(f"{path}: does not start with an OFF header (found {lines[0][:20]!r})")
    has_color = match.group(1).startswith("C")
    rest = match.group(2).split()
    body = lines[1:]
    if not rest:
        if not body:
            raise MeshLoadError(f"{path}: OFF header has no vertex/face counts")
        rest, body = body[0].split(), body[1:]
    try:
        n_vertices, n_faces = int(rest[0]), int(rest[1])
    except (ValueError, IndexError):
        raise MeshLoadError(f"{path}: bad OFF counts line {' '.join(rest)!r}") from None
    if n_vertices <= 0 or n_faces <= 0:
        raise MeshLoadError(f"{path}: OFF header declares {n_vertices} vertices and {n_faces} faces")
    if n_vertices * _MIN_OFF_VERTEX_BYTES + n_faces * _MIN_OFF_FACE_BYTES > len(data):
        raise MeshLoadError(
            f"{path}: header declares {n_vertices} vertices and {n_faces} faces, "
            f"more than a {len(data)}-byte file can hold (truncated or corrupt)"
        )
    if len(body) < n_vertices + n_faces:
        raise MeshLoadError(
            f"{path}: truncated: {n_vertices} vertices + {n_faces} faces declared, {len(body)} lines present"
        )
    try:
        vrows = [ln.split() for ln in body[:n_vertices]]
        vertices = np.array([[float(t) for t in row[:3]] for row in vrows], dtype=np.float64)
        colors = None
        if has_color and all(len(r) >= 6 for r in vrows):
            colors = np.array([[float(t) for t in row[3:6]] for row in vrows], dtype=np.float64)
            if colors.max(initial=0) > 1.0:
                colors = colors / 255.0
        triangles = []
        for ln in body[n_vertices : n_vertices + n_faces]:
            tok = ln.split()
            k = int(tok[0])
            if k < 3 or len(tok) < k + 1:
                raise MeshLoadError(f"{path}: bad OFF face line {ln[:40]!r}")
            idx = [int(t) for t in tok[1 : k + 1]]
            triangles.extend([idx[0], idx[i], idx[i + 1]] for i in range(1, k - 1))
    except (ValueError, IndexError):
        raise MeshLoadError(f"{path}: malformed OFF body (non-numeric or short vertex/face line)") from None
    if vertices.shape != (n_vertices, 3):
        raise MeshLoadError(f"{path}: vertex lines must hold 3 coordinates")
    return RawMesh(vertices, np.array(triangles, dtype=np.int64).reshape(-1, 3), colors)


def _check_header_counts(path: Path, suffix: str) -> None:
    """Refuse PLY/STL files whose declared element counts exceed what the file size can hold."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(4096)
    if suffix == ".ply":
        if not head.startswith(b"ply"):
            raise MeshLoadError(f"{path}: not a PLY file (missing 'ply' magic)")
        counts = [int(c) for c in re.findall(rb"element\s+\w+\s+(\d+)", head)]
        if sum(counts) > size:  # every element takes at least one byte, in any encoding
            raise MeshLoadError(f"{path}: PLY header declares {sum(counts)} elements in a {size}-byte file")
    elif suffix == ".stl" and not head.lstrip().startswith(b"solid") and size >= 84:
        n = int(np.frombuffer(head[80:84], dtype="<u4")[0])
        if 84 + 50 * n > size:
            raise MeshLoadError(f"{path}: binary STL declares {n} triangles, more than its {size} bytes hold")


def _read_open3d(path: Path) -> RawMesh:
    import open3d as o3d

    # Open3D prints warnings instead of raising; silence them, validate what comes back instead.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=True, print_progress=False)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    if len(vertices) == 0 or len(triangles) == 0:
        raise MeshLoadError(
            f"{path}: could not read any triangles (unparseable, mis-typed, or a point cloud; "
            f"got {len(vertices)} vertices, {len(triangles)} triangles)"
        )
    colors = None
    if mesh.has_vertex_colors():
        colors = np.asarray(mesh.vertex_colors, dtype=np.float64)
    elif mesh.has_textures() and mesh.has_triangle_uvs():
        colors = _texture_to_vertex_colors(mesh, len(vertices), len(triangles))
    return RawMesh(vertices, triangles, colors)


def _texture_to_vertex_colors(mesh, n_vertices: int, n_triangles: int) -> np.ndarray | None:
    """Sample the first texture at each triangle corner's UV and average per vertex (RGB in [0, 1])."""
    texture = np.asarray(mesh.textures[0])
    uvs = np.asarray(mesh.triangle_uvs)
    if texture.ndim != 3 or texture.size == 0 or len(uvs) != 3 * n_triangles or not np.isfinite(uvs).all():
        return None
    h, w = texture.shape[:2]
    px = np.clip((uvs[:, 0] % 1.0) * (w - 1), 0, w - 1).round().astype(int)
    # Open3D has already flipped v to image row order (checked on the YCB textures: no black lookups).
    py = np.clip((uvs[:, 1] % 1.0) * (h - 1), 0, h - 1).round().astype(int)
    corner_rgb = texture[py, px, :3].astype(np.float64) / (255.0 if texture.dtype == np.uint8 else 1.0)
    corner_vertex = np.asarray(mesh.triangles).reshape(-1)
    sums = np.zeros((n_vertices, 3))
    np.add.at(sums, corner_vertex, corner_rgb)
    counts = np.bincount(corner_vertex, minlength=n_vertices)[:, None]
    return np.divide(sums, counts, out=np.full_like(sums, 0.5), where=counts > 0)


def validate_arrays(vertices, triangles, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes, finiteness and index range; return float64 vertices and int32 triangles.

    Raises:
        InvalidMeshError: naming ``name`` and the problem.
    """
    v = np.asarray(vertices)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise InvalidMeshError(f"{name}: vertices must be a non-empty (V, 3) array, got shape {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise InvalidMeshError(f"{name}: triangles must be a non-empty (F, 3) array, got shape {t.shape}")
    if not np.issubdtype(t.dtype, np.integer) and not (np.all(np.isfinite(t)) and np.all(t == np.round(t))):
        raise InvalidMeshError(f"{name}: triangle indices must be integers")
    v = v.astype(np.float64, copy=False)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise InvalidMeshError(
            f"{name}: {int(bad.sum())} vertices are NaN or Inf (first at index {int(np.argmax(bad))})"
        )
    t = t.astype(np.int64, copy=False)
    lo, hi = int(t.min()), int(t.max())
    if lo < 0 or hi >= len(v):
        raise InvalidMeshError(
            f"{name}: face indices out of range [{lo}, {hi}] for {len(v)} vertices"
        )
    return np.ascontiguousarray(v), np.ascontiguousarray(t.astype(np.int32))


def _first_of_equal_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For (N, 3) rows: the sorted indices of each group's first row, and per row its group (0..G-1 in
    order of first occurrence). A lexsort and a neighbour comparison: 5-10x faster than
    ``np.unique(axis=0)``, which sorts the rows as opaque records."""
    order = np.lexsort(rows.T[::-1])
    ordered = rows[order]
    new = np.ones(len(rows), dtype=bool)
    new[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    group_sorted = np.cumsum(new) - 1
    # lexsort is stable, so the first row of each sorted group is its smallest original index.
    firsts = order[new]
    rank = np.empty(len(firsts), dtype=np.int64)
    rank[np.argsort(firsts, kind="stable")] = np.arange(len(firsts))
    group = np.empty(len(rows), dtype=np.int64)
    group[order] = rank[group_sorted]
    return np.sort(firsts), group


def repair(
    vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray | None, name: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Merge duplicate vertices, drop duplicate and zero-area faces and unreferenced vertices.

    The same clean-up as pymeshlab's ``meshing_remove_duplicate_vertices``, ``_duplicate_faces``,
    ``_null_faces`` and ``_unreferenced_vertices`` (``tests/perception/test_geometry.py`` compares them), in
    numpy, because pymeshlab can take the process down on user data. Vertices keep the order of their first
    occurrence and faces their order; colours follow their vertices (a merged vertex keeps the first colour).
    Duplicate faces are faces on the same three vertices in any order (the first is kept).

    Raises:
        InvalidMeshError: nothing with area is left.
    """
    v = np.asarray(vertices, dtype=np.float64) + 0.0  # + 0.0 turns -0.0 into 0.0: equal positions, equal keys
    t = np.asarray(triangles, dtype=np.int64)
    first, inverse = _first_of_equal_rows(v)
    t = inverse[t]  # groups are numbered in order of first occurrence: the new vertex indices
    v = v[first]
    c = None if colors is None else np.asarray(colors, dtype=np.float64)[first]
    keep, _ = _first_of_equal_rows(np.sort(t, axis=1))
    t = t[keep]
    # Zero area tested on coordinates scaled by a power of two (exact) to O(1): the squares in the area of a
    # mesh at 1e160 mm would overflow, at 1e-160 mm underflow, and drop every face.
    unit = np.ldexp(v, -int(np.frexp(np.abs(v).max())[1]))
    cross = np.cross(unit[t[:, 1]] - unit[t[:, 0]], unit[t[:, 2]] - unit[t[:, 0]])
    t = t[np.abs(cross).max(axis=1) > 0]
    if len(t) == 0:
        raise InvalidMeshError(f"{name}: no triangle with non-zero area is left after repair")
    used = np.zeros(len(v), dtype=bool)
    used[t.ravel()] = True
    index = np.cumsum(used) - 1
    t, v = index[t], v[used]
    c = None if c is None else c[used]
    if (len(v), len(t)) != (len(vertices), len(triangles)):
        log.debug("%s: repair %d->%d vertices, %d->%d triangles", name, len(vertices), len(v), len(triangles), len(t))
    return v, t, c
