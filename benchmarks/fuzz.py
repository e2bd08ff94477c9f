"""A file fuzzer for the mesh loader (``load_object``) and the point-cloud loader (``load_points``).

Seeds: small files written here in every format the loaders read (OFF, glued OFF, PLY ASCII / binary
little- and big-endian, OBJ with quads, STL ASCII / binary; PCD ASCII / binary, XYZ, XYZN, XYZRGB, PTS,
TXT, PLY, NPY, NPZ), plus, where the shared data is present, its smallest SHREC, PSB and YCB meshes (read
in place; their mutated copies go to the case folder). Families of cases:

- ``seed``: every seed unmodified (each must load);
- ``flip`` / ``insert`` / ``delete``: random bytes changed, inserted or deleted (half of them digits,
  signs and letters of ``nan``/``inf``, so ASCII files stay ASCII and reach the parsers);
- ``truncate``: cut at a random length;
- ``huge_count``: a header count (OFF, PLY element, PCD POINTS/WIDTH, binary STL, NPY shape) or an OBJ face
  index set to a huge or negative value (a loader that trusts it would allocate gigabytes);
- ``numbers``: numbers replaced by nan, inf, -0, 1e308, denormals, huge integers (text), or special
  float / int bit patterns written into the binary payload;
- ``random_bytes``: random content (half behind a format's magic) under every suffix;
- ``empty``: empty, blank and header-only files;
- ``wrong_extension``: a valid file of one format named with another suffix.

Every case runs in a child process (``python -m benchmarks.fuzz --child``) under an address-space limit
(``RLIMIT_AS`` = the child's own size after start-up + ``--memory-mb``) and a per-case CPU-time limit, many
cases per child. A child that dies (abort, segfault) or runs out of time is reported as the outcome of the
case it was running, and a fresh child goes on with the rest. Outcomes: ``refused`` (a VisuotactileError)
and ``loaded`` (an ObjectModel with finite vertices and unit normals, indices in range, the documented
size) pass; ``invalid`` (a loaded model breaking those), ``error`` (any other exception), ``memory``
(MemoryError: the limit was hit), ``crash`` and ``timeout`` fail.

    .venv/bin/python -m benchmarks.fuzz [--per-family N] [--seed S] [--no-real] [--json]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import select
import signal
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from benchmarks._common import DATA

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = (
    "seed", "flip", "insert", "delete", "truncate", "huge_count", "numbers", "random_bytes", "empty",
    "wrong_extension",
)
OUTCOMES = ("refused", "loaded", "invalid", "error", "memory", "crash", "timeout")
PASSING = frozenset({"refused", "loaded"})
MESH_SUFFIXES = (".off", ".obj", ".ply", ".stl")
POINT_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".txt", ".ply", ".npy", ".npz")
#: Loader keyword arguments: a coarse Poisson depth keeps a point case at ~0.1 s (depth 8: ~1 s); the
#: reading, validation, normals, surface and repair steps are the same code.
POINT_KWARGS = {"poisson_depth": 4}
HUGE = (2**31 - 1, 2**31, 2**32 + 3, 10**9, 10**12, 2**63 - 1, 2**64 + 1, 10**30, -1, -(2**31))
TEXT_NUMBERS = (b"nan", b"NaN", b"inf", b"-inf", b"-0", b"1e308", b"-1e308", b"1e309", b"1e-320", b"9" * 40, b"-1", b"0")
FLOAT_VALUES = (np.nan, np.inf, -np.inf, -0.0, 1e308, -1e308, 5e-324, 1e30, 1e-30)
INT_VALUES = (-1, 2**31 - 1, -(2**31), 1000000, 12)
#: Bytes that keep an ASCII file ASCII and reach the number parsers.
ALPHABET = b"0123456789.-+eE \n\tnaif#,/"
MAGICS = {
    ".off": b"OFF\n", ".ply": b"ply\nformat binary_little_endian 1.0\n", ".stl": b"solid x\n",
    ".obj": b"v ", ".pcd": b"# .PCD v0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 100\nDATA binary\n",
    ".npy": b"\x93NUMPY\x01\x00", ".npz": b"PK\x03\x04",
}


@dataclass
class Seed:
    """A valid file: its loader (``mesh`` or ``points``), format, bytes, and where it came from."""

    name: str
    loader: str
    suffix: str
    data: bytes
    path: str | None = None  # a real file, read in place
    body: int = 0  # where the payload starts (after the header)
    slots: list[tuple[int, str]] = field(default_factory=list)  # binary numbers: (offset, struct format)
    expect: tuple[int, int] | None = None  # (vertices, triangles) a mesh seed loads to


@dataclass
class Case:
    family: str
    loader: str
    path: str
    note: str
    expect: tuple[int, int] | None = None


@dataclass
class Result:
    case: Case
    outcome: str
    detail: str
    seconds: float
    peak_mb: float
    shape: tuple[int, int] | None = None


# ------------------------------------------------------------------------------------------ seeds
def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5**0.5) / 2
    v = np.array([
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
        [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]) * 10.0
    f = np.array([
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
        [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
        [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ])
    return v, f


def _ply_header(fmt: str, n_vertices: int, props: str, n_faces: int | None) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment fuzz seed", f"element vertex {n_vertices}", props]
    if n_faces is not None:
        lines += [f"element face {n_faces}", "property list uchar int vertex_indices"]
    return ("\n".join(lines + ["end_header"]) + "\n").encode()


def mesh_seeds() -> list[Seed]:
    """Hand-written meshes: an icosahedron (12 vertices, 20 triangles) in every format, a quad cube in OBJ."""
    v, f = _icosahedron()
    ico = (12, 20)
    seeds = []
    vtext = "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in v)
    ftext = "".join(f"3 {a} {b} {c}\n" for a, b, c in f)
    off = f"OFF\n# an icosahedron\n{len(v)} {len(f)} 0\n{vtext}{ftext}".encode()
    seeds.append(Seed("ico.off", "mesh", ".off", off, body=off.index(b"0\n", off.index(b"12 20")) + 2, expect=ico))
    glued = f"OFF{len(v)} {len(f)} 0\n{vtext}{ftext}".encode()
    seeds.append(Seed("ico-glued.off", "mesh", ".off", glued, body=glued.index(b"\n") + 1, expect=ico))
    props = "property float x\nproperty float y\nproperty float z"
    head = _ply_header("ascii", len(v), props + "\nproperty uchar red\nproperty uchar green\nproperty uchar blue", len(f))
    body = "".join(f"{x:.7g} {y:.7g} {z:.7g} 200 100 {i * 20}\n" for i, (x, y, z) in enumerate(v)) + ftext
    seeds.append(Seed("ico-ascii.ply", "mesh", ".ply", head + body.encode(), body=len(head), expect=ico))
    for fmt, end in (("binary_little_endian", "<"), ("binary_big_endian", ">")):
        head = _ply_header(fmt, len(v), props, len(f))
        verts = b"".join(struct.pack(end + "3f", *row) for row in v)
        faces = b"".join(struct.pack(end + "B3i", 3, *row) for row in f)
        slots = [(len(head) + 4 * k, end + "f") for k in range(3 * len(v))]
        slots += [(len(head) + len(verts) + 13 * i + 1 + 4 * k, end + "i") for i in range(len(f)) for k in range(3)]
        seeds.append(Seed(f"ico-{end == '<' and 'le' or 'be'}.ply", "mesh", ".ply", head + verts + faces,
                          body=len(head), slots=slots, expect=ico))
    vn = v / np.linalg.norm(v, axis=1, keepdims=True)
    obj = "# icosahedron with normals\no ico\n" + "".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in v)
    obj += "".join(f"vn {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vn)
    obj += "".join(f"f {a + 1}//{a + 1} {b + 1}//{b + 1} {c + 1}//{c + 1}\n" for a, b, c in f)
    seeds.append(Seed("ico.obj", "mesh", ".obj", obj.encode(), expect=ico))
    cube = "".join(f"v {x} {y} {z}\n" for x in (0, 10) for y in (0, 10) for z in (0, 10))
    cube += "f 1 2 4 3\nf 5 7 8 6\nf 1 5 6 2\nf 3 4 8 7\nf 1 3 7 5\nf 2 6 8 4\n"
    seeds.append(Seed("cube-quads.obj", "mesh", ".obj", cube.encode(), expect=(8, 12)))
    corners = np.array([[x, y, z] for x in (0, 10) for y in (0, 10) for z in (0, 10)], dtype=float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    head = _ply_header("ascii", 8, props, 6)
    body = "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in corners) + "".join(f"4 {a} {b} {c} {d}\n" for a, b, c, d in quads)
    seeds.append(Seed("cube-quads-ascii.ply", "mesh", ".ply", head + body.encode(), body=len(head), expect=(8, 12)))
    # Two quads split into triangles: lists of 3 and 4 entries (the row-by-row path of the PLY reader).
    mixed = quads[:4] + [[0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    head = _ply_header("binary_little_endian", 8, props, len(mixed))
    verts = corners.astype("<f4").tobytes()
    faces = b"".join(struct.pack(f"<B{len(q)}i", len(q), *q) for q in mixed)
    seeds.append(Seed("cube-mixed-le.ply", "mesh", ".ply", head + verts + faces, body=len(head),
                      slots=[(len(head) + 4 * k, "<f") for k in range(24)], expect=(8, 12)))
    quad_off = "OFF\n8 6 0\n" + "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in corners)
    quad_off += "".join(f"4 {a} {b} {c} {d}\n" for a, b, c, d in quads)
    seeds.append(Seed("cube-quads.off", "mesh", ".off", quad_off.encode(), body=len("OFF\n8 6 0\n"), expect=(8, 12)))
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    stl = "solid ico\n"
    for tri, nn in zip(f, n):
        stl += f" facet normal {nn[0]:.6g} {nn[1]:.6g} {nn[2]:.6g}\n  outer loop\n"
        stl += "".join(f"   vertex {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in v[tri])
        stl += "  endloop\n endfacet\n"
    seeds.append(Seed("ico-ascii.stl", "mesh", ".stl", (stl + "endsolid ico\n").encode(), expect=ico))
    blob = b"binary STL fuzz seed".ljust(80, b" ") + struct.pack("<I", len(f))
    blob += b"".join(struct.pack("<12fH", *nn, *v[tri].ravel(), 0) for tri, nn in zip(f, n))
    slots = [(84 + 50 * i + 4 * k, "<f") for i in range(len(f)) for k in range(12)]
    seeds.append(Seed("ico-binary.stl", "mesh", ".stl", blob, body=84, slots=slots, expect=ico))
    return seeds


def _cloud(n: int = 150) -> tuple[np.ndarray, np.ndarray]:
    """Points on an ellipsoid (20, 14, 10 mm) and their outward normals, from a fixed seed."""
    axes = np.array([20.0, 14.0, 10.0])
    d = np.random.default_rng(7).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    normals = d / axes
    return d * axes, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _npy_body(data: bytes) -> int:
    buf = io.BytesIO(data)
    major, _ = np.lib.format.read_magic(buf)
    (np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0)(buf)
    return buf.tell()


def point_seeds() -> list[Seed]:
    """Hand-written point clouds (150 points on an ellipsoid) in every point format."""
    p, nrm = _cloud()
    n = len(p)
    seeds = []
    pcd = ("# .PCD v0.7 - fuzz seed\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
           f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n")
    head = (pcd + "DATA ascii\n").encode()
    seeds.append(Seed("cloud-ascii.pcd", "points", ".pcd",
                      head + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in p).encode(), body=len(head)))
    head = (pcd + "DATA binary\n").encode()
    seeds.append(Seed("cloud-binary.pcd", "points", ".pcd", head + p.astype("<f4").tobytes(), body=len(head),
                      slots=[(len(head) + 4 * k, "<f") for k in range(3 * n)]))
    seeds.append(Seed("cloud.xyz", "points", ".xyz", "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in p).encode()))
    seeds.append(Seed("cloud.xyzn", "points", ".xyzn",
                      "".join(" ".join(f"{c:.6f}" for c in row) + "\n" for row in np.hstack([p, nrm])).encode()))
    rgb = np.hstack([p, (np.abs(nrm) * 255).round()])
    seeds.append(Seed("cloud.xyzrgb", "points", ".xyzrgb",
                      "".join(" ".join(f"{c:.6g}" for c in row) + "\n" for row in rgb).encode()))
    pts = f"{n}\n" + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in p)
    seeds.append(Seed("cloud.pts", "points", ".pts", pts.encode(), body=len(f"{n}\n")))
    seeds.append(Seed("cloud.txt", "points", ".txt", "".join(f"{x:.6f},{y:.6f},{z:.6f}\n" for x, y, z in p).encode()))
    props = "\n".join(f"property float {c}" for c in ("x", "y", "z", "nx", "ny", "nz"))
    head = _ply_header("ascii", n, props, None)
    body = "".join(" ".join(f"{c:.6f}" for c in row) + "\n" for row in np.hstack([p, nrm]))
    seeds.append(Seed("cloud-ascii.ply", "points", ".ply", head + body.encode(), body=len(head)))
    head = _ply_header("binary_little_endian", n, "property float x\nproperty float y\nproperty float z", None)
    seeds.append(Seed("cloud-le.ply", "points", ".ply", head + p.astype("<f4").tobytes(), body=len(head),
                      slots=[(len(head) + 4 * k, "<f") for k in range(3 * n)]))
    for name, array in (("cloud.npy", p), ("cloud-normals.npy", np.hstack([p, nrm]))):
        data = _npy(array)
        body = _npy_body(data)
        seeds.append(Seed(name, "points", ".npy", data, body=body,
                          slots=[(body + 8 * k, "<d") for k in range(array.size)]))
    for name, save, key in (("cloud.npz", np.savez, "points"), ("cloud-compressed.npz", np.savez_compressed, "xyz")):
        buf = io.BytesIO()
        save(buf, **{key: p, "normals": nrm})
        seeds.append(Seed(name, "points", ".npz", buf.getvalue()))
    return seeds


def real_seeds(data: Path = DATA) -> list[Seed]:
    """The smallest two SHREC 2007 and PSB meshes and the smallest YCB scan, read in place (none if absent)."""
    seeds = []
    for folder, pattern, count in (("shrec07", "*/*.off", 2), ("psb_open", "*.obj", 2), ("ycb", "*.obj", 1)):
        files = sorted((data / folder).glob(pattern), key=lambda p: (p.stat().st_size, p.name))[:count]
        for path in files:
            blob = path.read_bytes()
            body = 0
            if path.suffix == ".off":
                match = re.match(rb"\s*C?N?OFF\s*\d+\s+\d+(\s+\d+)?[^\n]*\n", blob)
                body = match.end() if match else 0
            seeds.append(Seed(f"{folder}-{path.parent.name}-{path.name}", "mesh", path.suffix, blob,
                              path=str(path), body=body))
    return seeds


# ------------------------------------------------------------------------------------ mutations
def _pick(rng: np.random.Generator, items):
    return items[int(rng.integers(len(items)))]


def _noise(rng: np.random.Generator, n: int) -> bytes:
    """``n`` bytes: uniformly random, or (half the time) from :data:`ALPHABET`."""
    if rng.random() < 0.5:
        return rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    return bytes(ALPHABET[i] for i in rng.integers(0, len(ALPHABET), n))


def flip(data: bytes, rng) -> tuple[bytes, str]:
    out = bytearray(data)
    k = int(rng.integers(1, 9))
    for i in rng.integers(0, len(out), k):
        new = _noise(rng, 1)[0]
        out[i] = new if new != out[i] else out[i] ^ 0x55
    return bytes(out), f"{k} bytes changed"


def insert(data: bytes, rng) -> tuple[bytes, str]:
    at = int(rng.integers(0, len(data) + 1))
    if rng.random() < 0.3:  # a copy of a span of the file itself (a repeated line, a doubled record)
        lo = int(rng.integers(0, len(data)))
        piece = data[lo : lo + int(rng.integers(1, 80))]
    else:
        piece = _noise(rng, int(rng.integers(1, 33)))
    return data[:at] + piece + data[at:], f"{len(piece)} bytes inserted at {at}"


def delete(data: bytes, rng) -> tuple[bytes, str]:
    at = int(rng.integers(0, len(data)))
    n = int(rng.integers(1, 65))
    return data[:at] + data[at + n :], f"{min(n, len(data) - at)} bytes deleted at {at}"


def truncate(data: bytes, rng) -> tuple[bytes, str]:
    n = int(rng.integers(1, len(data)))
    return data[:n], f"truncated to {n} of {len(data)} bytes"


def _npy_reshaped(data: bytes, shape: str) -> bytes:
    """An NPY file's bytes with the header's shape replaced by the text ``shape`` (payload unchanged)."""
    buf = io.BytesIO(data)
    np.lib.format.read_magic(buf)
    _, fortran, dtype = np.lib.format.read_array_header_1_0(buf)
    header = f"{{'descr': '{dtype.str}', 'fortran_order': {fortran}, 'shape': {shape}, }}"
    header += " " * ((-(len(header) + 11)) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + data[buf.tell() :]


def _npz_rebuilt(data: bytes, change) -> bytes:
    """The NPZ ``data`` with each member's bytes passed through ``change`` (a valid zip again)."""
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(out, "w") as dst:
        for i, info in enumerate(src.infolist()):
            dst.writestr(info.filename, change(i, src.read(info.filename)), compress_type=info.compress_type)
    return out.getvalue()


def huge_count(seed: Seed, rng) -> tuple[bytes, str] | None:
    """A header count (or an OBJ face index) set to a huge or negative value; None if the format has none."""
    data, value = seed.data, _pick(rng, HUGE)
    if seed.suffix == ".off":
        m = re.match(rb"(\s*C?N?OFF\s*)(\d+)(\s+)(\d+)", data)
        if not m:
            return None
        which = int(rng.integers(3))
        nv = str(value).encode() if which != 1 else m.group(2)
        nf = str(value).encode() if which != 0 else m.group(4)
        return m.group(1) + nv + m.group(3) + nf + data[m.end() :], f"OFF counts {nv.decode()} {nf.decode()}"
    if seed.suffix in (".ply", ".pcd"):
        key = rb"element \w+ " if seed.suffix == ".ply" else _pick(rng, [rb"POINTS ", rb"WIDTH ", rb"(?:POINTS|WIDTH) "])
        spans = [m.span(1) for m in re.finditer(rb"^" + key + rb"(\d+)", data[:4096], re.MULTILINE)]
        if not spans:
            return None
        lo, hi = _pick(rng, spans)
        line = data[data.rfind(b"\n", 0, lo) + 1 : hi].decode()
        return data[:lo] + str(value).encode() + data[hi:], f"header {line!r} -> {value}"
    if seed.suffix == ".stl" and seed.slots:
        n = _pick(rng, [2**32 - 1, 2**31, 10**9, 10**6, struct.unpack("<I", data[80:84])[0] + 1])
        return data[:80] + struct.pack("<I", n) + data[84:], f"binary STL count -> {n}"
    if seed.suffix == ".obj":
        spans = [m.span(1) for m in re.finditer(rb"^f\s+(\d+)", data, re.MULTILINE)]
        if not spans:
            return None
        lo, hi = _pick(rng, spans)
        index = _pick(rng, [10**9, 2**31, 2**63, -(10**9), 10**30])
        return data[:lo] + str(index).encode() + data[hi:], f"OBJ face index -> {index}"
    if seed.suffix in (".npy", ".npz"):
        shape = _pick(rng, [f"({value}, 3)", f"(150, {value})", "(150, 3, 1000000000)", "(-1, 3)", "(2**40,)"])
        if seed.suffix == ".npy":
            return _npy_reshaped(data, shape), f"NPY shape -> {shape}"
        return _npz_rebuilt(data, lambda i, b: _npy_reshaped(b, shape) if i == 0 else b), f"NPZ shape -> {shape}"
    return None


def numbers(seed: Seed, rng) -> tuple[bytes, str]:
    """Numbers replaced by special values: text tokens, binary payload slots, or an NPZ member's payload."""
    data = seed.data
    if seed.suffix == ".npz":
        def change(i, member):
            slots = [(_npy_body(member) + 8 * k, "<d") for k in range(8)]
            return _numbers_binary(member, slots, rng)[0] if i == 0 else member
        return _npz_rebuilt(data, change), "NPZ payload numbers -> special values"
    if seed.slots:
        return _numbers_binary(data, seed.slots, rng)
    tokens = [m.span() for m in re.finditer(rb"(?<![\w.])[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?![\w.])", data)]
    tokens = [t for t in tokens if t[0] >= seed.body] or tokens
    out, notes = data, []
    for lo, hi in sorted((_pick(rng, tokens) for _ in range(int(rng.integers(1, 4)))), reverse=True):
        new = _pick(rng, TEXT_NUMBERS)
        notes.append(f"{out[lo:hi].decode(errors='replace')}->{new.decode()}")
        out = out[:lo] + new + out[hi:]
    return out, "numbers " + ", ".join(notes)


def _numbers_binary(data: bytes, slots, rng) -> tuple[bytes, str]:
    out, notes = bytearray(data), []
    for _ in range(int(rng.integers(1, 4))):
        offset, fmt = _pick(rng, slots)
        if fmt[-1] in "fd":
            value = _pick(rng, FLOAT_VALUES)
            with np.errstate(over="ignore"):  # 1e308 as float32 is inf: fine, it is a special value too
                packed = np.array([value], dtype=fmt.replace("f", "f4").replace("d", "f8")).tobytes()
        else:
            value = _pick(rng, INT_VALUES)
            packed = struct.pack(fmt, value)
        out[offset : offset + len(packed)] = packed
        notes.append(f"@{offset}={value}")
    return bytes(out), "binary numbers " + ", ".join(notes)


def _empty_variants() -> list[tuple[str, str, bytes, str]]:
    """(loader, suffix, bytes, note): empty, blank and header-only files."""
    ply0 = b"ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
    pcd0 = b"# .PCD v0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA ascii\n"
    empty_npz = io.BytesIO()
    np.savez(empty_npz)
    npz0 = io.BytesIO()
    np.savez(npz0, points=np.zeros((0, 3)))
    out = [("mesh", s, b"", "empty") for s in MESH_SUFFIXES] + [("points", s, b"", "empty") for s in POINT_SUFFIXES]
    out += [
        ("mesh", ".off", b"\n \n\t\n", "blank"), ("mesh", ".off", b"OFF\n", "header only"),
        ("mesh", ".off", b"OFF\n0 0 0\n", "zero counts"), ("mesh", ".off", b"OFF\n3 1 0\n", "counts, no body"),
        ("mesh", ".ply", b"ply\nformat ascii 1.0\nend_header\n", "header only"), ("mesh", ".ply", ply0, "zero elements"),
        ("mesh", ".obj", b"# nothing\n", "comment only"), ("mesh", ".obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
        ("mesh", ".stl", b"solid a\nendsolid a\n", "no facets"),
        ("mesh", ".stl", b"\0" * 80 + struct.pack("<I", 0), "binary, zero triangles"),
        ("mesh", ".stl", b"\0" * 80, "binary, no count"),
        ("points", ".pcd", pcd0, "zero points"), ("points", ".xyz", b"\n \n", "blank"),
        ("points", ".pts", b"0\n", "count 0"), ("points", ".txt", b"# comment only\n", "comment only"),
        ("points", ".npy", _npy(np.zeros((0, 3))), "(0, 3) array"), ("points", ".npy", _npy(np.zeros(0)), "(0,) array"),
        ("points", ".npz", empty_npz.getvalue(), "no arrays"), ("points", ".npz", npz0.getvalue(), "(0, 3) points"),
        ("points", ".ply", ply0, "zero elements"),
    ]
    return out


def make_cases(folder: str | Path, per_family: int, *, seed: int = 0, real: bool = True) -> list[Case]:
    """Write the cases' files to ``folder``: every seed once, ``per_family`` cases of each mutation family
    (``empty`` at most once per variant); deterministic for a given ``seed``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    seeds = mesh_seeds() + point_seeds() + (real_seeds() if real else [])
    cases: list[Case] = []

    def add(family: str, loader: str, name: str, data: bytes, note: str, expect=None) -> None:
        path = folder / f"{len(cases):05d}-{family}-{name}"
        path.write_bytes(data)
        cases.append(Case(family, loader, str(path), note, expect))

    for s in seeds:
        if s.path is not None:
            cases.append(Case("seed", s.loader, s.path, f"{s.name} (in place)"))
        else:
            add("seed", s.loader, s.name, s.data, s.name, s.expect)
    for family, mutate in (("flip", flip), ("insert", insert), ("delete", delete), ("truncate", truncate)):
        for k in range(per_family):
            s = seeds[(k + int(rng.integers(len(seeds)))) % len(seeds)]
            data, note = mutate(s.data, rng)
            add(family, s.loader, s.name, data, f"{s.name}: {note}")
    for family, mutate in (("huge_count", huge_count), ("numbers", numbers)):
        usable = [s for s in seeds if mutate(s, np.random.default_rng(0)) is not None]
        for k in range(per_family):
            s = usable[(k + int(rng.integers(len(usable)))) % len(usable)]
            data, note = mutate(s, rng)
            add(family, s.loader, s.name, data, f"{s.name}: {note}")
    for k in range(per_family):
        loader = ("mesh", "points")[k % 2]
        suffix = _pick(rng, MESH_SUFFIXES if loader == "mesh" else POINT_SUFFIXES)
        data = _noise(rng, int(np.exp(rng.uniform(0, np.log(4096)))))
        if rng.random() < 0.5 and suffix in MAGICS:
            data = MAGICS[suffix] + data
        add("random_bytes", loader, f"random{suffix}", data, f"{len(data)} random bytes as {suffix}")
    variants = _empty_variants()
    for i in rng.permutation(len(variants))[:per_family]:
        loader, suffix, data, note = variants[i]
        add("empty", loader, f"empty{suffix}", data, f"{suffix}: {note}")
    for k in range(per_family):
        s = seeds[(k + int(rng.integers(len(seeds)))) % len(seeds)]
        others = [x for x in (*MESH_SUFFIXES, *POINT_SUFFIXES, ".bin", "") if x != s.suffix] + [s.suffix.upper()]
        suffix = _pick(rng, others)
        loader = "mesh" if suffix.lower() in MESH_SUFFIXES else "points"
        if suffix.lower() == ".ply" or suffix in (".bin", ""):
            loader = _pick(rng, ["mesh", "points"])
        add("wrong_extension", loader, Path(s.name).stem + suffix, s.data, f"{s.name} named {suffix or 'no suffix'!r}")
    return cases


# ------------------------------------------------------------------------------------ the child
def _selftest(kind: str):
    """Loaders that misbehave on purpose: they show the harness reports what it should."""
    from perception.errors import MeshLoadError

    if kind == "_abort":
        os.abort()
    if kind == "_segfault":
        import ctypes

        ctypes.string_at(0)
    if kind == "_hang":
        while True:  # burns CPU, as a stuck parser would
            pass
    if kind == "_alloc":
        block = np.ones(1 << 31, dtype=np.uint8)  # 2 GiB, touched: past any limit of --memory-mb < 2048
        raise MeshLoadError(f"allocated {block.nbytes} bytes: the memory limit was not enforced")
    raise MeshLoadError("refused on purpose")


def _check_model(model, expect_size: float) -> str | None:
    """What is wrong with a loaded model (None if nothing): finiteness, ranges, unit normals, its size."""
    from perception.geometry import surface_centroid

    v, t = np.asarray(model.vertices), np.asarray(model.triangles)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        return f"bad shapes {v.shape} {t.shape}"
    if not np.isfinite(v).all():
        return "non-finite vertices"
    if t.min() < 0 or t.max() >= len(v):
        return f"indices out of range [{t.min()}, {t.max()}] for {len(v)} vertices"
    # Documented: unit vertex normals (isolated vertices get (0, 0, 1)); unit face normals, zero for faces
    # whose cross product is zero (degenerate).
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    for name, unit in (("vertex_normals", np.ones(len(v), bool)), ("triangle_normals", (cross != 0).any(axis=1))):
        n = np.asarray(getattr(model, name))
        if n.shape != (len(unit), 3) or not np.isfinite(n).all():
            return f"{name}: bad shape or non-finite"
        length = np.linalg.norm(n, axis=1)
        if np.abs(length[unit] - 1).max(initial=0) > 1e-6 or (length[~unit] != 0).any():
            return f"{name}: not unit length (or not zero for a degenerate face)"
    # The pose-free size: the diameter of the sphere about the surface centroid that holds every vertex.
    size = 2.0 * float(np.linalg.norm(v - surface_centroid(v, t), axis=1).max())
    if abs(size - expect_size) > 1e-6 * expect_size:
        return f"size (enclosing-sphere diameter about the surface centroid) {size!r}, expected {expect_size}"
    return None


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def _reset_peak() -> None:
    try:  # Linux >= 4.0: "5" resets VmHWM, so the peak below is this case's
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def _child(manifest: str, start: int, fd: int, memory_mb: int) -> None:
    import faulthandler
    import resource

    faulthandler.enable()  # a native crash prints the Python stack to the log the parent reads
    out = os.fdopen(fd, "w", buffering=1)
    cases = [Case(**c) for c in json.loads(Path(manifest).read_text())]
    kinds = {c.loader for c in cases[start:]}
    loaders = {}
    size = None
    if kinds & {"mesh", "points"}:
        from perception.errors import VisuotactileError
        from perception.geometry import DEFAULT_SIZE_MM, load_object
        from perception.reconstruct.surface import load_points, points_to_model

        size = DEFAULT_SIZE_MM
        loaders = {"mesh": load_object, "points": lambda p: load_points(p, **POINT_KWARGS)}
        # Warm up (thread pools, allocator arenas) before the limit, so that it bounds the cases only.
        points_to_model(_cloud()[0], **POINT_KWARGS)
    else:
        from perception.errors import VisuotactileError
    limit = _status_kb("VmSize") * 1024 + memory_mb * 2**20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    out.write(json.dumps({"ready": True, "rss_mb": _status_kb("VmRSS") / 1024, "limit_mb": limit / 2**20}) + "\n")
    for i in range(start, len(cases)):
        case = cases[i]
        _reset_peak()
        began = time.perf_counter()
        shape = None
        try:
            load = loaders.get(case.loader) or (lambda p, kind=case.loader: _selftest(kind))
            model = load(case.path)
            problem = _check_model(model, size)
            outcome, detail = ("invalid", problem) if problem else ("loaded", "")
            shape = (len(model.vertices), len(model.triangles))
        except VisuotactileError as exc:
            outcome, detail = "refused", f"{type(exc).__name__}: {exc}"
        except MemoryError as exc:
            outcome, detail = "memory", f"MemoryError: {exc}"
        except Exception as exc:  # noqa: BLE001 - anything else is what the fuzzer looks for
            import traceback

            where = traceback.extract_tb(exc.__traceback__)[-1]
            outcome, detail = "error", f"{type(exc).__name__}: {exc} (at {Path(where.filename).name}:{where.lineno})"
        record = {"i": i, "outcome": outcome, "detail": detail[:300], "seconds": time.perf_counter() - began,
                  "peak_mb": _status_kb("VmHWM") / 1024, "shape": shape}
        out.write(json.dumps(record) + "\n")
    out.close()


# ------------------------------------------------------------------------------------ the parent
def _cpu_seconds(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def _log_tail(path: Path, lines: int = 4) -> str:
    """The child log's fatal-error line and the innermost frames after it (faulthandler), or its last lines."""
    try:
        text = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    fatal = next((k for k, ln in enumerate(text) if ln.startswith("Fatal Python error")), None)
    return " | ".join(text[-lines:] if fatal is None else text[fatal : fatal + lines])


def run_cases(
    cases: list[Case], *, timeout_s: float = 30.0, memory_mb: int = 1024, startup_s: float = 120.0,
    progress=None,
) -> list[Result]:
    """Run ``cases`` in child processes (many per child); a child that crashes or overruns is replaced.

    ``timeout_s`` is CPU seconds per case (a starved child on a busy machine is not timed out; a wall
    limit of 20 x that still catches a child blocked in a wait). ``memory_mb``: the address space a case
    may add to the child's size after start-up. ``progress(n)`` is called with each finished case count.
    """
    results: list[Result | None] = [None] * len(cases)
    with tempfile.TemporaryDirectory(prefix="fuzz-") as tmp:
        manifest = Path(tmp) / "cases.json"
        manifest.write_text(json.dumps([asdict(c) for c in cases]))
        start = 0
        while start < len(cases):
            start = _run_child(manifest, cases, start, results, timeout_s, memory_mb, startup_s, Path(tmp), progress)
    return results  # type: ignore[return-value]


#: Per child started: its resident size after start-up and its address-space limit (MB).
CHILDREN: list[dict] = []


def _run_child(manifest, cases, start, results, timeout_s, memory_mb, startup_s, tmp, progress) -> int:
    """One child from case ``start`` on; returns where the next child must start."""
    def result(i: int, record: dict) -> Result:
        return Result(cases[i], record["outcome"], record["detail"], record["seconds"], record["peak_mb"],
                      tuple(record["shape"]) if record["shape"] else None)

    env = {**os.environ, "OMP_NUM_THREADS": "1", "MALLOC_ARENA_MAX": "2", "PYTHONPATH": str(ROOT)}
    return supervise_child("benchmarks.fuzz", manifest, start, memory_mb, cwd=ROOT, env=env, cases=cases,
                           results=results, result=result, result_type=Result, timeout_s=timeout_s,
                           startup_s=startup_s, log_path=tmp / f"child-{start}.log", progress=progress)


def supervise_child(module: str, manifest, start: int, memory_mb: int, *, cwd, env: dict, cases, results, result,
                    result_type, timeout_s: float, startup_s: float, log_path: Path, progress) -> int:
    """Run ``python -m module --child manifest start fd memory_mb`` and fill ``results`` from the JSON lines it
    writes on ``fd`` (``result(i, record)`` makes each entry) until it ends, crashes or overruns ``timeout_s`` CPU
    seconds on a case (``startup_s`` before it says ready; 20 x that in wall time); the case it was on is then a
    ``result_type`` "timeout" or "crash". Returns where the next child must start. Shared by the fuzzers."""
    read_fd, write_fd = os.pipe()
    with open(log_path, "wb") as log:
        child = subprocess.Popen(
            [sys.executable, "-m", module, "--child", str(manifest), str(start), str(write_fd), str(memory_mb)],
            cwd=cwd, stdin=subprocess.DEVNULL, stdout=log, stderr=log, pass_fds=(write_fd,), env=env,
        )
    os.close(write_fd)
    i, ready, buffer = start, False, b""
    limit = startup_s
    case_began, cpu_began = time.monotonic(), _cpu_seconds(child.pid)
    try:
        while True:
            ready_fds, _, _ = select.select([read_fd], [], [], 0.5)
            if ready_fds:
                chunk = os.read(read_fd, 1 << 16)
                if not chunk:
                    break  # the child exited or died
                buffer += chunk
                *lines, buffer = buffer.split(b"\n")
                for line in lines:
                    record = json.loads(line)
                    if record.get("ready"):
                        ready, limit = True, timeout_s
                        CHILDREN.append({"rss_mb": record["rss_mb"], "limit_mb": record["limit_mb"]})
                    else:
                        i = record["i"]
                        results[i] = result(i, record)
                        i += 1
                        if progress:
                            progress(1)
                    case_began, cpu_began = time.monotonic(), _cpu_seconds(child.pid)
                continue
            cpu = _cpu_seconds(child.pid) - cpu_began
            wall = time.monotonic() - case_began
            if cpu > limit or wall > 20 * limit:
                child.kill()
                child.wait()
                if not ready:
                    raise RuntimeError(f"fuzz child did not start: {_log_tail(log_path)}")
                results[i] = result_type(cases[i], "timeout", f"over {limit:g} s of CPU ({cpu:.1f} s) or "
                                         f"{20 * limit:g} s of wall time ({wall:.1f} s)", wall, float("nan"))
                if progress:
                    progress(1)
                return i + 1
    finally:
        os.close(read_fd)
    code = child.wait()
    if i >= len(cases):
        return i
    if not ready:
        raise RuntimeError(f"fuzz child died starting (exit {code}): {_log_tail(log_path)}")
    how = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit {code}"
    results[i] = result_type(cases[i], "crash", f"child died ({how}): {_log_tail(log_path)}"[:600],
                             time.monotonic() - case_began, float("nan"))
    if progress:
        progress(1)
    return i + 1


# ------------------------------------------------------------------------------------ reporting
def outcome_summary(results, key, outcomes, order) -> dict:
    """Per ``key(result)``: case count, outcome counts (``outcomes``), the median and largest per-case peak RSS (MB;
    NaN without any) and the longest case (s); rows sorted by ``order(name)``. Shared with
    :mod:`benchmarks.fuzz_files`."""
    table = {}
    for r in results:
        row = table.setdefault(key(r), {"cases": 0, **dict.fromkeys(outcomes, 0), "peaks_mb": [], "max_seconds": 0.0})
        row["cases"] += 1
        row[r.outcome] += 1
        if np.isfinite(r.peak_mb):
            row["peaks_mb"].append(r.peak_mb)
        row["max_seconds"] = max(row["max_seconds"], r.seconds)
    for row in table.values():
        peaks = row.pop("peaks_mb")
        row["median_peak_mb"] = float(np.median(peaks)) if peaks else float("nan")
        row["max_peak_mb"] = float(np.max(peaks)) if peaks else float("nan")
    return dict(sorted(table.items(), key=lambda kv: order(kv[0])))


def outcome_table(summary: dict, outcomes, label: str) -> str:
    """:func:`outcome_summary` as a plain-text table with a total row."""
    width = max(len(label), *(len(name) for name in summary)) + 2 if summary else len(label) + 2
    rows = [f"{label:<{width}} {'cases':>6} " + " ".join(f"{o:>8}" for o in outcomes)
            + f"  {'peak MB (median / max)':>22} {'max s':>7}"]
    total = Counter()
    for name, row in summary.items():
        rows.append(f"{name:<{width}} {row['cases']:>6} " + " ".join(f"{row[o]:>8}" for o in outcomes)
                    + f"  {row['median_peak_mb']:>14.0f} / {row['max_peak_mb']:<5.0f} {row['max_seconds']:>7.2f}")
        total.update({k: row[k] for k in ("cases", *outcomes)})
    rows.append(f"{'total':<{width}} {total['cases']:>6} " + " ".join(f"{total[o]:>8}" for o in outcomes))
    return "\n".join(rows)


def summarize(results: list[Result]) -> dict:
    """Per family and loader (:func:`outcome_summary`)."""
    return outcome_summary(results, lambda r: f"{r.case.family}/{r.case.loader}", OUTCOMES,
                           lambda name: (FAMILIES.index(name.split("/")[0]), name))


def failures(results: list[Result]) -> list[Result]:
    return [r for r in results if r.outcome not in PASSING]


def format_table(summary: dict) -> str:
    return outcome_table(summary, OUTCOMES, "family/loader")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        _child(argv[1], int(argv[2]), int(argv[3]), int(argv[4]))
        return 0
    parser = argparse.ArgumentParser(prog="fuzz", description=__doc__.splitlines()[0])
    parser.add_argument("--per-family", type=int, default=125, help="cases per mutation family (default 125)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=30.0, help="CPU seconds per case (default 30)")
    parser.add_argument("--memory-mb", type=int, default=1024, help="address space a case may add (default 1024)")
    parser.add_argument("--no-real", action="store_true", help="leave out the shared data's meshes")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    began = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fuzz-cases-") as folder:
        cases = make_cases(folder, args.per_family, seed=args.seed, real=not args.no_real)
        results = run_cases(cases, timeout_s=args.timeout, memory_mb=args.memory_mb)
    summary = summarize(results)
    bad = failures(results)
    if args.json:
        print(json.dumps({"benchmark": "fuzz", "cases": len(results), "seconds": time.perf_counter() - began,
                          "memory_mb": args.memory_mb, "timeout_s": args.timeout, "summary": summary,
                          "failures": [{**asdict(r.case), "outcome": r.outcome, "detail": r.detail} for r in bad]},
                         indent=1, default=str))
    else:
        print(format_table(summary))
        print(f"\n{len(results)} cases in {time.perf_counter() - began:.0f} s, {len(CHILDREN)} child process(es); "
              f"per case: <= {args.timeout:g} CPU s, <= {args.memory_mb} MB address space above the child's "
              f"start-up size (RSS {CHILDREN[0]['rss_mb']:.0f} MB, limit {CHILDREN[0]['limit_mb']:.0f} MB)")
        for r in bad:
            print(f"FAIL {r.case.family} {r.case.loader} {Path(r.case.path).name} ({r.case.note}): {r.outcome}: {r.detail}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
