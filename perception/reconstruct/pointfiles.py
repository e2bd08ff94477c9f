"""Point-cloud files: :func:`read_points` and :func:`write_points` (PCD, XYZ/XYZN/XYZRGB/PTS, PLY, NPY/NPZ), mm."""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
import open3d as o3d

from perception import meshio
from perception.errors import MeshLoadError
from perception.reconstruct.points import _as_points

#: File suffixes :func:`read_points` understands.
POINT_SUFFIXES = frozenset({".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt", ".ply", ".npy", ".npz"})


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
        InvalidMeshError: bad point array (see :func:`~perception.reconstruct.points.validate_points`, without the size and shape checks).
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


__all__ = ["POINT_SUFFIXES", "read_points", "write_points"]
