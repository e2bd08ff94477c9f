"""Reading, validating and repairing mesh files (OFF, OBJ, PLY, STL).

Why not hand everything to Open3D: its ``read_triangle_mesh`` never raises on a bad file (it returns an
empty or partial mesh and accepts out-of-range indices), its PLY reader segfaults on damaged face lists and
returns unread vertices uninitialised, it drops OBJ polygons, and pymeshlab can take the whole process down
on a malformed file. So OFF (including ModelNet's glued ``OFF216 183 0`` header and polygon faces), PLY
(ASCII and binary) and OBJ files with polygons are parsed here; triangle OBJ (with textures) and STL go
through Open3D and are validated afterwards; header counts are checked against the file size before
anything is allocated, and pymeshlab only ever sees arrays validated here. ``benchmarks/fuzz.py`` fuzzes
these readers.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception.errors import InvalidMeshError, MeshLoadError
from perception.limits import LIMITS, limit

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
    """``path`` as a Path and its lower-case suffix, after checking it names a non-empty file of a known type and
    of at most the ``file_mb`` limit (:mod:`perception.limits`; checked from its size, before it is read).

    Raises:
        MeshLoadError: missing, a directory, an unknown suffix, empty or too large; the message names ``kind``.
    """
    path = Path(path)
    if not path.exists():
        raise MeshLoadError(f"{path}: no such file")
    if path.is_dir():
        raise MeshLoadError(f"{path}: is a directory, not a {kind} file")
    suffix = path.suffix.lower()
    if suffix not in suffixes:
        raise MeshLoadError(f"{path}: unknown {kind} type {suffix!r} (expected one of {sorted(suffixes)})")
    size = path.stat().st_size
    if size == 0:
        raise MeshLoadError(f"{path}: file is empty")
    top = limit("file_mb")
    if size > top * 2**20:
        raise MeshLoadError(f"{path}: {size / 2**20:,.0f} MB, above the limit of {top:,} MB per {kind} file (set "
                            f"{LIMITS['file_mb'].env} to raise it)")
    return path, suffix


def read_mesh(path: Path) -> RawMesh:
    """Read a mesh file into arrays; polygon faces are fan-triangulated.

    Raises:
        MeshLoadError: missing file, directory, unknown suffix, or a file that cannot be parsed.
    """
    path, suffix = check_file(path, "mesh", MESH_SUFFIXES)
    if suffix == ".off":
        return read_off(path)
    if suffix == ".ply":
        return _ply_mesh(path)
    _check_header_counts(path, suffix)
    if suffix == ".obj" and _OBJ_POLYGON.search(path.read_bytes()):
        return _read_obj_polygons(path)
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
        vertex_lines, face_lines = body[:n_vertices], body[n_vertices : n_vertices + n_faces]
        vertices, colors = _off_vertices(vertex_lines, has_color)
        triangles = _off_triangles(path, face_lines)
    except (ValueError, IndexError, OverflowError):  # OverflowError: an index beyond int64
        raise MeshLoadError(f"{path}: malformed OFF body (non-numeric or short vertex/face line)") from None
    if vertices.shape != (n_vertices, 3):
        raise MeshLoadError(f"{path}: vertex lines must hold 3 coordinates")
    return RawMesh(vertices, triangles, colors)


def _tokens_of_rows(lines: list[str], width: int) -> list[str] | None:
    """The tokens of ``lines`` in one flat list when every line holds exactly ``width`` of them, else None. One
    split of the joined text: a ``#`` between lines (comments are already cut, so no line holds one) must fall
    after every ``width`` tokens, so a short line beside a long one cannot pass for two rows."""
    tokens = " # ".join(lines).split()
    n = len(lines)
    if len(tokens) != (width + 1) * n - 1 or tokens[width :: width + 1].count("#") != n - 1:
        return None
    del tokens[width :: width + 1]
    return tokens


def _off_vertices(lines: list[str], has_color: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(V, 3) coordinates and, for COFF lines that carry them, (V, 3) colours in [0, 1], from OFF vertex lines.
    numpy parses each token as Python's ``float`` does; a file of bare ``x y z`` lines is parsed in one call."""
    tokens = _tokens_of_rows(lines, 3)
    if tokens is not None:
        try:
            return np.array(tokens, dtype=np.float64).reshape(-1, 3), None
        except ValueError:
            pass  # the line-by-line path raises it again
    rows = [ln.split() for ln in lines]
    vertices = np.array([row[:3] for row in rows], dtype=np.float64)
    colors = None
    if has_color and all(len(r) >= 6 for r in rows):
        colors = np.array([row[3:6] for row in rows], dtype=np.float64)
        if colors.max(initial=0) > 1.0:
            colors = colors / 255.0
    return vertices, colors


def _off_triangles(path: Path, lines: list[str]) -> np.ndarray:
    """(T, 3) int64 vertex indices from OFF face lines, polygons fanned from their first vertex. numpy parses each
    token as Python's ``int`` does; a file of bare triangle lines (``3 a b c``) is parsed in one call."""
    tokens = _tokens_of_rows(lines, 4)
    if tokens is not None:
        try:
            faces = np.array(tokens, dtype=np.int64).reshape(-1, 4)
        except (ValueError, OverflowError):
            faces = None  # the line-by-line path names the line or the body
        if faces is not None and (faces[:, 0] == 3).all():
            return np.ascontiguousarray(faces[:, 1:])
    triangles = []
    for ln in lines:
        tok = ln.split()
        k = int(tok[0])
        if k < 3 or len(tok) < k + 1:
            raise MeshLoadError(f"{path}: bad OFF face line {ln[:40]!r}")
        idx = [int(t) for t in tok[1 : k + 1]]
        triangles.extend([idx[0], idx[i], idx[i + 1]] for i in range(1, k - 1))
    return np.array(triangles, dtype=np.int64).reshape(-1, 3)


def _check_header_counts(path: Path, suffix: str) -> None:
    """Refuse binary STL files whose declared triangle count exceeds what the file size can hold."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(4096)
    if suffix == ".stl" and not head.lstrip().startswith(b"solid") and size >= 84:
        n = int(np.frombuffer(head[80:84], dtype="<u4")[0])
        if 84 + 50 * n > size:
            raise MeshLoadError(f"{path}: binary STL declares {n} triangles, more than its {size} bytes hold")


# PLY is parsed here, not by Open3D: its reader segfaults on a binary PLY whose face lists are damaged, and
# on a short or malformed file it returns the arrays at full size with the unread part uninitialised.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
_PLY_ENDIAN = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class PlyElement:
    """One element of a PLY header: name, row count, and properties as (name, dtype, list-count dtype or None)."""

    name: str
    count: int
    properties: list[tuple[str, str, str | None]]


def _ply_header(path: Path, data: bytes) -> tuple[str | None, list[PlyElement], int]:
    """The endianness (None for ASCII), the elements, and the offset of the body."""
    end = re.search(rb"(?:^|\n)end_header[ \t\r]*(?:\n|$)", data)
    if not data.startswith(b"ply") or end is None:
        raise MeshLoadError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' line)")
    try:
        lines = data[: end.start()].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise MeshLoadError(f"{path}: PLY header is not ASCII text") from None
    fmt, elements = "", []
    for line in lines:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format" and len(words) == 3 and words[1] in _PLY_ENDIAN:
                fmt = words[1]
            elif words[0] == "element" and len(words) == 3 and int(words[2]) >= 0:
                elements.append(PlyElement(words[1], int(words[2]), []))
            elif words[0] == "property" and elements and len(words) == 3:
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]], None))
            elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
                elements[-1].properties.append((words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
            else:
                raise ValueError
        except (ValueError, KeyError):
            raise MeshLoadError(f"{path}: bad PLY header line {line[:60]!r}") from None
    if not fmt:
        raise MeshLoadError(f"{path}: PLY header has no 'format ascii|binary_little_endian|binary_big_endian' line")
    return _PLY_ENDIAN[fmt], elements, end.end()


def read_ply(path: str | Path) -> dict[str, dict[str, np.ndarray | list[np.ndarray]]]:
    """Parse a PLY file (ASCII or binary): per element, per property, an array of its rows (a list
    property: an (N, k) array when every row has k entries, else a list of arrays).

    Raises:
        MeshLoadError: not a PLY file, a bad header, counts the file cannot hold, short or malformed data.
    """
    path = Path(path)
    data = path.read_bytes()
    endian, elements, offset = _ply_header(path, data)
    # Bounded resources: every row takes at least a byte (binary) or a token of two bytes (ASCII).
    total = sum(e.count for e in elements)
    if total * (1 if endian else 2) > len(data) - offset:
        raise MeshLoadError(
            f"{path}: PLY header declares {total} elements, more than the {len(data)}-byte file holds"
        )
    out = {}
    if endian is None:
        try:
            lines = [ln for ln in data[offset:].decode("ascii").splitlines() if ln.strip()]
        except UnicodeDecodeError:
            raise MeshLoadError(f"{path}: ASCII PLY body holds non-ASCII bytes (corrupt?)") from None
        row = 0
        for element in elements:
            out[element.name] = _ply_ascii(path, element, lines[row : row + element.count])
            row += element.count
    else:
        for element in elements:
            out[element.name], offset = _ply_binary(path, element, data, offset, endian)
    return out


def _ply_ascii(path: Path, element: PlyElement, lines: list[str]) -> dict:
    """One element's rows from its ASCII lines (one row a line, as every writer does)."""
    if len(lines) < element.count:
        raise MeshLoadError(f"{path}: truncated PLY: {element.count} {element.name} rows declared, {len(lines)} present")
    props = element.properties
    try:  # fixed width (every row as long): numpy's C parser; it refuses ragged or non-numeric rows
        table = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments=None) if lines else None
    except ValueError:
        table = None
    try:
        if table is not None:
            out, col = {}, 0
            for name, dtype, count_type in props:
                if count_type is None:
                    out[name], col = _ply_cast(path, table[:, col], dtype), col + 1
                    continue
                k = table[:, col] if col < table.shape[1] else None
                if k is None or (k != k[0]).any() or not (0 <= k[0] <= table.shape[1] and k[0] == int(k[0])):
                    break  # ragged lists (or a short row): row by row below
                out[name] = _ply_cast(path, table[:, col + 1 : col + 1 + int(k[0])], dtype)
                col += 1 + int(k[0])
            else:
                if col == table.shape[1]:
                    return out
        columns: list[list[np.ndarray]] = [[] for _ in props]
        for r in (ln.split() for ln in lines):  # ragged lists (polygons of several sizes): row by row
            col = 0
            for j, (_, _, count_type) in enumerate(props):
                k = 1 if count_type is None else int(r[col])
                col += count_type is not None
                if k < 0 or col + k > len(r):
                    raise ValueError
                columns[j].append(np.array(r[col : col + k], dtype=np.float64))
                col += k
            if col != len(r):
                raise ValueError
    except (ValueError, IndexError, OverflowError):
        raise MeshLoadError(f"{path}: malformed ASCII PLY {element.name} rows (non-numeric or wrong length)") from None
    out = {}
    for (name, dtype, count_type), values in zip(props, columns):
        if count_type is None:
            out[name] = _ply_cast(path, np.concatenate(values) if values else np.zeros(0), dtype)
        else:
            out[name] = [_ply_cast(path, v, dtype) for v in values]
    return out


def _ply_cast(path: Path, values: np.ndarray, dtype: str) -> np.ndarray:
    """ASCII values as their declared type; integers must be integral and in range."""
    if dtype[0] == "f":
        with np.errstate(over="ignore"):  # 1e39 as a float is inf: the validation names it
            return values.astype(dtype)
    info = np.iinfo(dtype)
    if not (np.isfinite(values).all() and (values == np.round(values)).all()
            and (values >= info.min).all() and (values <= info.max).all()):
        raise MeshLoadError(f"{path}: a PLY {dtype} property holds a value that is not such an integer")
    return values.astype(dtype)


def _ply_binary(path: Path, element: PlyElement, data: bytes, offset: int, endian: str) -> tuple[dict, int]:
    """One element's rows from binary data at ``offset``; returns them and the offset after them."""
    short = MeshLoadError(f"{path}: truncated or corrupt binary PLY ({element.name} rows run past the end)")
    props = element.properties
    # Fixed layout (lists as long as in the first row): one numpy read, then every row's lengths checked.
    fields, lists, pos = [], [], offset
    for i, (_, dtype, count_type) in enumerate(props):
        if count_type is None:
            fields.append((f"p{i}", endian + dtype))
            pos += np.dtype(dtype).itemsize
            continue
        if pos + np.dtype(count_type).itemsize > len(data):
            raise short
        k = int(np.frombuffer(data, endian + count_type, 1, pos)[0]) if element.count else 0
        if k < 0 or k > len(data):
            raise MeshLoadError(f"{path}: bad list length {k} in binary PLY {element.name} rows")
        fields += [(f"c{i}", endian + count_type), (f"p{i}", endian + dtype, (k,))]
        lists.append((i, k))
        pos += np.dtype(count_type).itemsize + k * np.dtype(dtype).itemsize
    layout = np.dtype(fields)
    end = offset + element.count * layout.itemsize
    if end <= len(data):
        rows = np.frombuffer(data, layout, element.count, offset)
        if all((rows[f"c{i}"] == k).all() for i, k in lists):
            return {name: rows[f"p{i}"].copy() for i, (name, _, _) in enumerate(props)}, end
    # Ragged lists: row by row, every length checked against what is left.
    columns: list[list[np.ndarray]] = [[] for _ in props]
    for _ in range(element.count):
        for j, (_, dtype, count_type) in enumerate(props):
            k = 1
            if count_type is not None:
                if offset + np.dtype(count_type).itemsize > len(data):
                    raise short
                k = int(np.frombuffer(data, endian + count_type, 1, offset)[0])
                offset += np.dtype(count_type).itemsize
            size = k * np.dtype(dtype).itemsize
            if k < 0 or offset + size > len(data):
                raise short
            columns[j].append(np.frombuffer(data, endian + dtype, k, offset))
            offset += size
    out = {}
    for (name, dtype, count_type), values in zip(props, columns):
        out[name] = values if count_type else np.concatenate(values or [np.zeros(0, dtype)])
    return out, offset


def _ply_mesh(path: Path) -> RawMesh:
    """A mesh from a PLY file: vertex x, y, z, optional colours, polygon faces fan-triangulated."""
    elements = read_ply(path)
    vertex = elements.get("vertex", {})
    if not {"x", "y", "z"} <= set(vertex):
        raise MeshLoadError(f"{path}: PLY file has no vertex element with x, y, z")
    vertices = np.column_stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"])
    face = elements.get("face", {})
    lists = face.get("vertex_indices", face.get("vertex_index"))
    triangles = _fan(lists if lists is not None else np.zeros((0, 3), np.int64))
    if len(triangles) == 0:
        raise MeshLoadError(f"{path}: could not read any triangles (a PLY point cloud, or no face element)")
    colors = None
    for names in (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if set(names) <= set(vertex):
            columns = [np.asarray(vertex[c]) for c in names]
            colors = np.column_stack(columns).astype(np.float64)
            if columns[0].dtype.kind in "iu":
                colors /= float(np.iinfo(columns[0].dtype).max)
            break
    return RawMesh(vertices, triangles, colors)


def _fan(lists) -> np.ndarray:
    """(F, 3) int64 triangles from polygon index lists (an (N, k) array or a list of arrays) by fan triangulation;
    lists of fewer than three indices are dropped."""
    groups = [np.asarray(lists)] if isinstance(lists, np.ndarray) else [np.asarray(a)[None] for a in lists]
    out = []
    for g in groups:
        if g.ndim == 2 and g.shape[1] >= 3:
            g = g.astype(np.int64)
            out += [np.column_stack([g[:, 0], g[:, i], g[:, i + 1]]) for i in range(1, g.shape[1] - 1)]
    return np.concatenate(out) if out else np.zeros((0, 3), np.int64)


#: An OBJ face line with four or more corners (Open3D drops such faces: "non-triangle primitive").
_OBJ_POLYGON = re.compile(rb"^f(?:[ \t]+\S+){4,}", re.MULTILINE)


def _read_obj_polygons(path: Path) -> RawMesh:
    """An OBJ with polygon faces: ``v`` and ``f`` lines (``i``, ``i/t``, ``i//n``, ``i/t/n``, negative =
    relative), fan-triangulated. Textures are not read on this path."""
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise MeshLoadError(f"{path}: not a text OBJ file (binary or corrupt content)") from None
    vertices, faces = [], []
    try:
        for line in text.splitlines():
            words = line.split()
            if not words:
                continue
            if words[0] == "v" and len(words) >= 4:
                vertices.append([float(w) for w in words[1:4]])
            elif words[0] == "f" and len(words) >= 4:
                idx = [int(w.split("/")[0]) for w in words[1:]]
                idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]  # 1-based; negative counts back
                faces += [[idx[0], idx[i], idx[i + 1]] for i in range(1, len(idx) - 1)]
        triangles = np.array(faces, dtype=np.int64).reshape(-1, 3)
    except (ValueError, OverflowError):
        raise MeshLoadError(f"{path}: malformed OBJ vertex or face line (non-numeric)") from None
    if not vertices or len(triangles) == 0:
        raise MeshLoadError(f"{path}: could not read any triangles ({len(vertices)} vertices, {len(triangles)} faces)")
    log.debug("%s: polygon faces; read without Open3D (textures ignored)", path)
    return RawMesh(np.array(vertices, dtype=np.float64), triangles)


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
