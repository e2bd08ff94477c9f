"""The procedural object catalogue: the toolkit's embedded default data (no downloads, no data files).

Ten classes of everyday hand-held objects, each an unlimited family of watertight instances drawn from a
seed: dimensions, proportions and details (handle, rim, lid, ribs, foot, bevels) vary within the class.
The classes differ in the local geometry a finger meets: flat faces and rounded edges (box), cylinders with
beads and ribs (can, bottle), thin walls with rounded rims and concave insides (mug, bowl, funnel,
wineglass, spoon), handles and holes (mug, ring), bars and wedges (hammer).

Construction: profiles are drawn in 2D (fillets, curves, manifold3d ``CrossSection`` offsets and unions for
walls of constant thickness), turned into surfaces of revolution by our own mesher (:func:`_lathe`), whose
rings carry as many vertices as their circumference needs, so triangles stay near-isotropic and vertices
evenly spread (a plain revolve puts as many vertices on a ring near the axis as on the rim, with needle
triangles there). Parts that are not surfaces of revolution (handles, hammer heads, lids) are joined with
manifold3d booleans, which keep the mesh closed and consistently oriented.

Resolution: every object is meshed at a 150 mm size (the enclosing-sphere diameter about its surface centroid) with an edge length chosen from its
area (2 to 4 mm, aiming at ~6000 triangles; 6k-15k in practice), finer where the surface turns quickly:
steps of at most 15 degrees around rings and along profiles, down to ``edge / 8`` on small fillets and
rims. The facets then depart from the intended surface by about 0.1 mm at most (chord sagitta), well below
the 0.6 mm pitch of a 32 x 32, 20 mm tactile pad. A different ``size_mm`` scales the whole mesh.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Callable
from pathlib import Path

import manifold3d as mf
import numpy as np

from perception.atomic import save_figure
from perception.errors import DatasetError, InvalidArgumentError, InvalidMeshError
from perception.geometry import DEFAULT_SIZE_MM, ObjectModel, normalize, surface_centroid
from perception.runtime import progress_bar

log = logging.getLogger(__name__)

#: Bounds of the target edge length on a 150 mm object, mm.
EDGE_RANGE_MM = (2.0, 4.0)

#: The triangle count the edge length aims at (rims and fillets add to it).
TARGET_TRIANGLES = 6000

#: Largest angle between the facets around a ring or along a fillet, degrees.
_MAX_TURN_DEG = 15.0

#: Edges shorter than this (at the 150 mm build size) are collapsed, mm.
_TINY_EDGE_MM = 1e-3

#: The size (ObjectModel.size) objects are meshed at before the final scaling, mm.
_BUILD_MM = 150.0

Builder = Callable[[float], mf.Manifold]


# ------------------------------------------------------------------------------------------- 2D helpers
def _fillet(points: np.ndarray, radii, closed: bool = True) -> np.ndarray:
    """Replace corner i of a polyline by a circular arc of radius ``radii[i]`` (0: keep the corner).

    Arcs turn at most ``_MAX_TURN_DEG`` per step; a radius shrinks where its arc would not fit in half of
    each neighbouring segment.
    """
    p = np.asarray(points, dtype=np.float64)
    n = len(p)
    out: list[np.ndarray] = []
    for i in range(n):
        r = float(radii[i])
        if r <= 0 or (not closed and i in (0, n - 1)):
            out.append(p[i][None])
            continue
        corner = p[i]
        u, v = p[i - 1] - corner, p[(i + 1) % n] - corner
        lu, lv = np.linalg.norm(u), np.linalg.norm(v)
        u, v = u / lu, v / lv
        half = 0.5 * np.arccos(np.clip(u @ v, -1.0, 1.0))  # half the interior angle
        if half < 1e-6 or np.pi / 2 - half < 1e-6:  # a cusp or a straight line: nothing to round
            out.append(corner[None])
            continue
        tangent = min(r / np.tan(half), 0.5 * lu, 0.5 * lv)
        r = tangent * np.tan(half)
        centre = corner + (u + v) / np.linalg.norm(u + v) * r / np.sin(half)
        a0 = np.arctan2(*(corner + u * tangent - centre)[::-1])
        a1 = np.arctan2(*(corner + v * tangent - centre)[::-1])
        sweep = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
        k = max(2, int(np.ceil(abs(sweep) / np.radians(_MAX_TURN_DEG))))
        angles = a0 + sweep * np.linspace(0.0, 1.0, k + 1)
        out.append(centre + r * np.stack([np.cos(angles), np.sin(angles)], axis=1))
    return np.concatenate(out)


def _curve(fn: Callable[[np.ndarray], np.ndarray], spacing: float, n_dense: int = 1000) -> np.ndarray:
    """Points of the parametric curve ``fn(s)``, s in [0, 1], at equal arc length <= ``spacing``."""
    dense = fn(np.linspace(0.0, 1.0, n_dense))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    n = max(2, int(np.ceil(arc[-1] / spacing)) + 1)
    at = np.linspace(0.0, arc[-1], n)
    return np.stack([np.interp(at, arc, dense[:, 0]), np.interp(at, arc, dense[:, 1])], axis=1)


def _resample(path: np.ndarray, edge: float, closed: bool) -> np.ndarray:
    """Resample a polyline so that steps are at most ``edge`` long and turn at most 15 degrees.

    Steps are no shorter than ``edge / 8`` (noise and tiny arcs are merged) except at sharp corners (over
    40 degrees), which are kept exactly, as are the end points of an open path.
    """
    p = np.asarray(path, dtype=np.float64)
    # Offsets leave near-duplicate points (micro zigzags): merge them, keeping the end points.
    near = np.r_[False, np.linalg.norm(np.diff(p, axis=0), axis=1) <= edge / 100]
    if not closed and near[-1]:
        near[-2:] = [True, False]
    p = p[~near]
    if closed:
        p = p[:-1] if np.linalg.norm(p[-1] - p[0]) <= 1e-9 else p
        p = np.vstack([p, p[:1]])
    # A fine polyline through every input vertex, to pick the output points from.
    seg = np.diff(p, axis=0)
    pieces = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / (edge / 8)).astype(int))
    which = np.repeat(np.arange(len(seg)), pieces)
    frac = (np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)) / pieces[which]
    fine = np.vstack([p[which] + seg[which] * frac[:, None], p[-1:]])
    step = np.diff(fine, axis=0)
    length = np.linalg.norm(step, axis=1)
    heading = np.arctan2(step[:, 1], step[:, 0])
    turn = np.abs((np.diff(heading) + np.pi) % (2 * np.pi) - np.pi)  # at fine vertices 1 .. n-2
    max_turn, corner_turn = np.radians(_MAX_TURN_DEG), np.radians(40.0)
    keep, arc, turned, movable = [0], 0.0, 0.0, False
    for k in range(1, len(fine) - 1):
        arc += length[k - 1]
        turned += turn[k - 1]
        corner = turn[k - 1] > corner_turn
        if corner and arc < edge / 8 and movable:
            keep[-1] = k  # a corner just after a smooth point replaces it: no needle-thin ring strip
        elif corner or arc + length[k] > edge or (turned >= max_turn and arc >= edge / 8):
            keep.append(k)
        else:
            continue
        arc, turned, movable = 0.0, 0.0, not corner
    if closed:
        # The start stays (lofts align rings on it). A short closing step would make a thin strip between
        # nearly parallel rings: share the last two steps evenly instead, unless the last point is a corner.
        gap = arc + length[-1]
        if len(keep) > 3 and turn[keep[-1] - 1] <= corner_turn:
            along = np.concatenate([[0.0], np.cumsum(length)])
            if gap < 0.5 * (along[keep[-1]] - along[keep[-2]]):
                keep[-1] = int(np.argmin(np.abs(along - 0.5 * (along[keep[-2]] + along[-1]))))
        return fine[keep]
    return fine[keep + [len(fine) - 1]]


def _mirror(half: np.ndarray) -> np.ndarray:
    """A polygon symmetric about x = 0 from a path that runs from the axis, through x > 0, back to it."""
    return np.vstack([half, half[-2:0:-1] * [-1.0, 1.0]])


def _section(points: np.ndarray) -> mf.CrossSection:
    """A cross-section from one simple polygon, turned counter-clockwise (positive fill) if needed."""
    p = np.asarray(points, dtype=np.float64)
    area2 = np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
    return mf.CrossSection([p if area2 > 0 else p[::-1].copy()])


def _arc_segments(radius: float, edge: float) -> int:
    """Segments of a full circle so that steps are at most ``edge`` long and turn at most 15 degrees."""
    return max(round(360 / _MAX_TURN_DEG), int(np.ceil(2 * np.pi * radius / edge)))


def _offset(section: mf.CrossSection, delta: float, edge: float) -> mf.CrossSection:
    return section.offset(delta, mf.JoinType.Round, circular_segments=_arc_segments(abs(delta), edge))


def _open(section: mf.CrossSection, radius: float, edge: float) -> mf.CrossSection:
    """Round every convex corner with ``radius`` (a morphological opening)."""
    return _offset(_offset(section, -radius, edge), radius, edge)


def _close(section: mf.CrossSection, radius: float, edge: float) -> mf.CrossSection:
    """Round every concave corner with ``radius`` (a morphological closing)."""
    return _offset(_offset(section, radius, edge), -radius, edge)


def _vessel(
    outer: np.ndarray, thickness: float, edge: float, open_bottom: bool = False
) -> tuple[mf.CrossSection, mf.CrossSection]:
    """Symmetric (r, z) sections of a thin-walled vessel and of the solid inside mid-wall.

    ``outer`` is the outer surface (x >= 0) from the bottom (on the axis, or the edge of a bottom opening
    when ``open_bottom``) up to the rim, its last point. The wall lies inside it, ``thickness`` thick, with
    fully rounded rims. The mid-wall solid, extended above the rim, trims parts such as handles so that
    they end inside the wall.
    """
    outer = np.asarray(outer, dtype=np.float64)
    rim_r, rim_z = outer[-1]
    margin = 4 * thickness + 10.0
    half = np.vstack([[outer[0, 0], outer[0, 1] - margin], outer]) if open_bottom else outer
    mirrored = half[::-1] * [-1.0, 1.0]
    if not open_bottom:
        mirrored = mirrored[:-1]  # the axis point is shared
    # The region above the outer surface; its inward offset is the cavity, the band between them the wall.
    region = _section(np.vstack([half, [[rim_r, rim_z + margin], [-rim_r, rim_z + margin]], mirrored]))
    width = 2 * float(np.max(np.abs(outer[:, 0]))) + 2 * margin
    z0 = float(outer[0, 1]) - (0.0 if open_bottom else 1.0)
    clip = mf.CrossSection.square((width, rim_z - z0)).translate((-width / 2, z0))
    wall = (region - _offset(region, -thickness, edge)) ^ clip
    return _open(wall, 0.45 * thickness, edge), _offset(region, -thickness / 2, edge)


# ------------------------------------------------------------------------------------------- 3D helpers
def _zip(a: np.ndarray, b: np.ndarray, ta: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """Triangles joining two rings of vertex indices ``a``, ``b`` at increasing parameters ``ta``, ``tb``.

    Parameters are fractions of a turn, each ring's within [t[0], t[0] + 1), both rings starting near 0.

    Walk both rings together, always advancing the one whose next vertex comes first (a zipper); a ring of
    one vertex is a pole (a fan).
    """
    na, nb = len(a), len(b)
    empty = np.zeros(0)
    nxt_a = np.append(ta[1:], ta[0] + 1.0) if na > 1 else empty
    nxt_b = np.append(tb[1:], tb[0] + 1.0) if nb > 1 else empty
    on_b = np.concatenate([np.zeros(len(nxt_a), bool), np.ones(len(nxt_b), bool)])
    order = np.lexsort((on_b, np.concatenate([nxt_a, nxt_b])))
    on_b = on_b[order]
    i = np.cumsum(~on_b) - ~on_b  # steps taken on a before this one
    j = np.cumsum(on_b) - on_b
    tri_a = np.stack([a[i % na], a[(i + 1) % na], b[j % nb]], axis=1)
    tri_b = np.stack([a[i % na], b[(j + 1) % nb], b[j % nb]], axis=1)
    return np.where(on_b[:, None], tri_b, tri_a)


def _tube(
    rings: list[np.ndarray], closed: bool = False, params: list[np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh through closed rings of 3D points (one point: a pole), each starting at the same side.

    Consecutive rings are zipped by ``params`` (fractions of a turn per vertex; default: arc-length
    fractions from each ring's first vertex); ``closed`` joins the last ring to the first (a torus),
    otherwise the first and last rings must be poles. Returns vertices and triangles (orientation
    arbitrary).
    """
    if params is None:
        params = []
        for ring in rings:
            chord = np.linalg.norm(np.diff(ring, axis=0, append=ring[:1]), axis=1)
            arc = np.cumsum(chord) - chord  # arc length up to each vertex
            params.append(arc / chord.sum() if len(ring) > 1 else np.zeros(1))
    indices, start = [], 0
    for ring in rings:
        indices.append(np.arange(start, start + len(ring)))
        start += len(ring)
    pairs = list(range(len(rings) - 1)) + ([len(rings) - 1] if closed else [])
    tris = [
        _zip(indices[k], indices[(k + 1) % len(rings)], params[k], params[(k + 1) % len(rings)])
        for k in pairs
    ]
    return np.concatenate(rings), np.concatenate(tris)


def _lathe(
    profile: np.ndarray, edge: float, *, closed: bool = False, aspect: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the surface swept by the (r, z) ``profile`` around z, with sections ``aspect`` times as wide in y.

    An open profile must start and end on the axis (r = 0, the poles); a ``closed`` one (a loop off the
    axis) gives a torus-like surface. Each ring has enough vertices for chords of at most ``edge`` and
    facets at most 15 degrees apart. Returns vertices (V, 3) and triangles (F, 3), orientation arbitrary.
    """
    p = np.asarray(profile, dtype=np.float64)
    r, z = p[:, 0], p[:, 1]
    tangent = np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0) if closed else np.gradient(p, axis=0)
    # How much the normal points away from the axis: the facets around a ring turn by that times the step.
    radial = np.abs(tangent[:, 1]) / np.maximum(np.linalg.norm(tangent, axis=1), 1e-12)
    stretch = max(aspect, 1 / aspect)
    need = np.maximum.reduce(
        [
            np.full(len(r), 8.0),
            2 * np.pi * r * stretch / edge,
            360 / _MAX_TURN_DEG * radial * np.sqrt(stretch),
        ]
    )
    counts = 4 * np.ceil(need / 4).astype(int)
    rings, params = [], []
    for ri, zi, n in zip(r, z, counts):
        if ri <= 1e-9:
            rings.append(np.array([[0.0, 0.0, zi]]))
            params.append(np.zeros(1))
            continue
        # Half a step off the x axis: no vertex on the plane y = 0, where other parts (lofts, handles)
        # have theirs; coincident vertices in a boolean give near-degenerate, even overlapping, triangles.
        turn = (np.arange(n) + 0.5) / n
        theta = 2 * np.pi * turn
        rings.append(np.stack([ri * np.cos(theta), aspect * ri * np.sin(theta), np.full(n, zi)], axis=1))
        params.append(turn)
    return _tube(rings, closed, params)


def _rounded_rect(half_w: float, half_h: float, radius: float, edge: float) -> np.ndarray:
    """Counter-clockwise outline (M, 2) of a rectangle with rounded corners, starting at (half_w, 0).

    ``radius`` is clipped to the half sizes, so equal sizes and radius give a circle, ``radius = half_h``
    a stadium.
    """
    radius = min(radius, half_w, half_h)
    cx, cy = half_w - radius, half_h - radius
    outline = []
    for quarter, (sx, sy) in enumerate([(1, 1), (-1, 1), (-1, -1), (1, -1)]):
        a = np.radians(90 * quarter) + np.linspace(
            0, 0.5 * np.pi, max(2, int(np.ceil(90 / _MAX_TURN_DEG))) + 1
        )
        outline.append(np.stack([sx * cx + radius * np.cos(a), sy * cy + radius * np.sin(a)], 1))
    closed_path = np.vstack([[[half_w, 0.0]], *outline, [[half_w, 0.0]]])
    return _resample(closed_path, edge, closed=True)


def _loft(
    stations: np.ndarray, outlines: list[np.ndarray], start: float | None = None, end: float | None = None
) -> mf.Manifold:
    """Solid through planar outlines (M_i, 2) at heights ``stations`` along z, closed by a pole at each end.

    The poles lie at heights ``start`` and ``end`` (default: the first and last station, flat caps).
    """
    start = stations[0] if start is None else start
    end = stations[-1] if end is None else end
    rings = [np.array([[0.0, 0.0, start]])]
    rings += [np.c_[o, np.full(len(o), z)] for z, o in zip(stations, outlines)]
    rings.append(np.array([[0.0, 0.0, end]]))
    return _manifold(*_tube(rings))


def _manifold(vertices: np.ndarray, triangles: np.ndarray) -> mf.Manifold:
    """A manifold3d solid from a closed mesh, turned outward (positive signed volume) if needed."""
    v0, v1, v2 = (vertices[triangles[:, k]] for k in range(3))
    if np.einsum("ij,ij->", v0, np.cross(v1, v2)) < 0:
        triangles = triangles[:, ::-1]
    # One face id per triangle: otherwise manifold3d treats coplanar triangles as one face and, after a
    # boolean, re-triangulates flat regions with long thin triangles.
    mesh = mf.Mesh64(
        vert_properties=np.ascontiguousarray(vertices, dtype=np.float64),
        tri_verts=np.ascontiguousarray(triangles, dtype=np.uint64),
        face_id=np.arange(len(triangles), dtype=np.uint64),
    )
    return mf.Manifold(mesh)


def _revolve(profile: np.ndarray, edge: float, *, closed: bool = False, aspect: float = 1.0) -> mf.Manifold:
    """Solid of revolution about z of an (r, z) profile (see :func:`_lathe`), resampled for ``edge``."""
    return _manifold(*_lathe(_resample(profile, edge, closed), edge, closed=closed, aspect=aspect))


def _revolve_section(section: mf.CrossSection, edge: float) -> mf.Manifold:
    """Solid of revolution about z of the x >= 0 half of a symmetric section with one outline."""
    width, height = 1e4, 1e4
    half = section ^ mf.CrossSection.square((width, height)).translate((0.0, -height / 2))
    (poly,) = half.to_polygons()
    on_axis = np.abs(poly[:, 0]) < 1e-6
    if not on_axis.any():
        return _revolve(poly, edge, closed=True)
    # Start right after the run of axis vertices, so that the path goes axis -> x > 0 -> axis.
    first = int(np.flatnonzero(on_axis & ~np.roll(on_axis, -1))[0])
    path = np.roll(poly, -first, axis=0)
    off = np.abs(path[:, 0]) >= 1e-6
    last = int(np.flatnonzero(off)[-1]) + 1
    path = path[: last + 1].copy()
    path[[0, -1], 0] = 0.0
    return _revolve(path, edge)


def _revolve_coarse(section: mf.CrossSection, radius: float, edge: float) -> mf.Manifold:
    """manifold3d's revolve of a section (for trimming solids, whose surface does not show), turned half a
    step so that, like :func:`_lathe`, it has no vertex on the plane y = 0."""
    n = _arc_segments(radius, edge)
    return section.revolve(n).rotate((0.0, 0.0, 180.0 / n))


def _rounded_box(lo, hi, radius: float, edge: float) -> mf.Manifold:
    """Box from corner ``lo`` to ``hi`` (mm) with edges and corners rounded by ``radius``.

    A grid on the cube's faces, even on the flat parts and even in angle across the rounded ones, is
    pushed onto the rounded surface: every vertex moves to ``radius`` from the inner box, along the
    direction away from it (flat-face vertices do not move).
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    inner = half - radius
    steps = max(3, int(np.ceil(max(np.pi / 4 * radius / edge, 45 / _MAX_TURN_DEG))))
    steps = min(steps, max(1, int(np.ceil(np.pi / 4 * radius / (edge / 8)))))
    axes = []
    ramp = inner[:, None] + radius * np.tan(np.radians(45.0) * np.arange(1, steps + 1) / steps)[None]
    for k in range(3):
        flat = np.linspace(-inner[k], inner[k], max(1, int(np.ceil(2 * inner[k] / edge))) + 1)
        line = np.concatenate([-ramp[k, ::-1], flat, ramp[k]])
        line[[0, -1]] = -half[k], half[k]  # exactly on the faces, so that shared edges merge
        axes.append(line)
    vertices, triangles, start = [], [], 0
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        nb, nc = len(axes[b]), len(axes[c])
        idx = np.arange(nb * nc).reshape(nb, nc)
        q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
        quads = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
        for sign in (-1.0, 1.0):
            grid = np.zeros((nb, nc, 3))
            grid[..., a] = sign * half[a]
            grid[..., b], grid[..., c] = np.meshgrid(axes[b], axes[c], indexing="ij")
            vertices.append(grid.reshape(-1, 3))
            triangles.append(start + (quads if sign > 0 else quads[:, ::-1]))  # (b, c, a) is right-handed
            start += nb * nc
    vertices, inverse = np.unique(np.concatenate(vertices), axis=0, return_inverse=True)
    core = np.clip(vertices, -inner, inner)
    away = vertices - core
    norm = np.linalg.norm(away, axis=1, keepdims=True)
    vertices = core + radius * away / np.maximum(norm, 1e-12)
    return _manifold(vertices + centre, inverse.reshape(-1)[np.concatenate(triangles)])


# ---------------------------------------------------------------------------------------- the classes
# Each takes a random generator, draws all its parameters, and returns a builder: edge length (mm) -> solid.
# Dimensions are in mm for an object of about the final size; the result is rescaled anyway.
def _bottle(rng: np.random.Generator) -> Builder:
    """Body, optional waist, shoulder, neck and screw cap; a concave punt under the base."""
    body_r, body_h = rng.uniform(24, 36), rng.uniform(60, 95)
    shoulder_h, neck_r, neck_h = rng.uniform(18, 40), rng.uniform(9, 14), rng.uniform(10, 25)
    cap_r, cap_h = neck_r + rng.uniform(1.0, 3.0), rng.uniform(10, 18)
    waist = rng.uniform(1.5, 4.0) if rng.random() < 0.5 else 0.0
    shoulder_power, punt = rng.uniform(0.6, 1.6), rng.uniform(1.0, 5.0)
    z_lo, z_hi = body_h * rng.uniform(0.3, 0.45), body_h * rng.uniform(0.6, 0.85)
    base_edge, cap_edge = rng.uniform(3, 8), rng.uniform(1.0, 3.0)

    def side(s):  # body wall with an optional smooth waist
        z = s * body_h
        bump = np.where((z > z_lo) & (z < z_hi), np.sin(np.pi * (z - z_lo) / (z_hi - z_lo)) ** 2, 0.0)
        return np.stack([body_r - waist * bump, z], axis=1)

    def shoulder(s):
        u = s**shoulder_power
        return np.stack(
            [neck_r + (body_r - neck_r) * 0.5 * (1 + np.cos(np.pi * u)), body_h + shoulder_h * s], 1
        )

    def build(edge: float) -> mf.Manifold:
        z_neck = body_h + shoulder_h + neck_h
        body = np.vstack([_curve(side, edge), _curve(shoulder, edge / 2)[1:]])
        pts = np.vstack(
            [
                [[0, punt], [body_r * 0.7, 0.0]],
                body,
                [[neck_r, z_neck], [cap_r, z_neck], [cap_r, z_neck + cap_h], [0, z_neck + cap_h]],
            ]
        )
        radii = np.zeros(len(pts))
        radii[1], radii[2] = 2.0, base_edge
        radii[-4:] = [0.6, 0.6, cap_edge, 0.0]
        return _revolve(_fillet(pts, radii), edge)

    return build


def _bowl(rng: np.random.Generator) -> Builder:
    """A shallow vessel: flat bottom blending into a power-law wall, sometimes a foot ring."""
    rim_r, height = rng.uniform(55, 70), rng.uniform(35, 65)
    flat_r, power, thickness = rim_r * rng.uniform(0.25, 0.5), rng.uniform(1.6, 3.0), rng.uniform(3.0, 6.0)
    foot = rng.random() < 0.6
    foot_r, foot_w, foot_h = flat_r * rng.uniform(0.7, 0.95), rng.uniform(3, 6), rng.uniform(3, 8)

    def wall(s):
        return np.stack([flat_r + s * (rim_r - flat_r), height * s**power], axis=1)

    def build(edge: float) -> mf.Manifold:
        section, _ = _vessel(np.vstack([[0.0, 0.0], _curve(wall, edge)]), thickness, edge)
        if foot:
            ring = np.array(
                [[foot_r - foot_w, -foot_h], [foot_r, -foot_h], [foot_r, 1.0], [foot_r - foot_w, 1.0]]
            )
            ring = _fillet(ring, [1.5, 1.5, 0, 0])
            section = _close(section + _section(ring) + _section(ring * [-1, 1]), 1.5, edge)
        return _revolve_section(section, edge)

    return build


def _box(rng: np.random.Generator) -> Builder:
    """A rounded box, sometimes with a lid that overhangs it all round."""
    size = np.array([rng.uniform(60, 110), 0.0, rng.uniform(25, 90)])
    size[1] = rng.uniform(35, size[0])
    rounding = rng.uniform(1.0, min(8.0, size[2] / 6))
    lid = rng.random() < 0.5
    overhang = rng.uniform(0.8, 2.5)
    lid_h = max(rng.uniform(0.12, 0.3) * size[2], 2 * (rounding + overhang) + 3.0)

    def build(edge: float) -> mf.Manifold:
        half = size / 2
        box = _rounded_box(-half, half, rounding, edge)
        if not lid:
            return box
        # The lid: the body's box grown by the overhang over its top, rounded a little less than concentric
        # (grid lines of both boxes in the same planes give near-degenerate triangles where they meet).
        lid_r = rounding + 0.5 * overhang
        # Its rounded bottom edge meets the body's walls at z_meet. Moving the lid by under half a grid step
        # puts that line midway between two of the body's grid lines: no sliver triangles along it.
        bottom = half[2] - lid_h
        z_meet = bottom + lid_r - np.sqrt(lid_r**2 - max(lid_r - overhang, 0.0) ** 2)
        inner = half[2] - rounding
        step = 2 * inner / max(1, int(np.ceil(2 * inner / edge)))
        bottom += -inner + (np.floor((z_meet + inner) / step) + 0.5) * step - z_meet
        lo = np.array([-half[0] - overhang, -half[1] - overhang, bottom])
        hi = np.array([half[0] + overhang, half[1] + overhang, half[2] + overhang])
        return box + _rounded_box(lo, hi, lid_r, edge)

    return build


def _can(rng: np.random.Generator) -> Builder:
    """A drinks can (tapered base and neck, recessed lid) or a food can (straight wall with ribs)."""
    radius, height = rng.uniform(28, 40), rng.uniform(90, 130)
    dome, lid_depth = rng.uniform(1.5, 5.0), rng.uniform(2, 6)
    drink = rng.random() < 0.5
    base_h = rng.uniform(5, 10) if drink else rng.uniform(1.5, 3)
    neck_h = rng.uniform(8, 15) if drink else rng.uniform(1.5, 3)
    neck_in = rng.uniform(3, 6) if drink else rng.uniform(0.5, 1.5)
    n_ribs = 0 if drink else int(rng.integers(2, 8))
    rib_depth, rib_w = rng.uniform(0.6, 1.5), rng.uniform(3, 6)

    def build(edge: float) -> mf.Manifold:
        z0, z1 = base_h, height - neck_h
        wall = [[radius, z0]]
        for c in z0 + (z1 - z0) * (np.arange(n_ribs) + 0.5) / n_ribs:
            s = np.linspace(-1, 1, 41)  # a smooth groove, finely sampled across its width
            wall.extend(np.stack([radius - rib_depth * np.cos(0.5 * np.pi * s) ** 2, c + s * rib_w / 2], 1))
        wall.append([radius, z1])
        top_r = radius - neck_in
        pts = np.vstack(
            [
                [[0, dome], [radius - base_h * 0.5 - 2, 0.0]],
                wall,
                [
                    [top_r + 0.8, height],
                    [top_r - 1.5, height],
                    [top_r - 2.3, height - lid_depth],
                    [0, height - lid_depth],
                ],
            ]
        )
        radii = np.zeros(len(pts))
        radii[1] = 1.5
        radii[2] = radii[1 + len(wall)] = 4.0 if drink else 1.0
        radii[-4:] = [0.7, 0.7, 1.0, 0.0]
        return _revolve(_fillet(pts, radii), edge)

    return build


def _funnel(rng: np.random.Generator) -> Builder:
    """A thin cone on a spout tube, open at both ends, sometimes with a vertical collar."""
    top_r, spout_r = rng.uniform(45, 65), rng.uniform(6, 11)
    cone_h, spout_h = rng.uniform(40, 70), rng.uniform(25, 55)
    thickness = rng.uniform(2.0, min(4.0, spout_r - 3.0))
    collar = rng.uniform(5, 15) if rng.random() < 0.5 else 0.0
    bend, collar_bend = rng.uniform(4, 12), rng.uniform(2, 6)

    def build(edge: float) -> mf.Manifold:
        pts = [[spout_r, 0.0], [spout_r, spout_h], [top_r, spout_h + cone_h]]
        radii = [0.0, bend, 0.0]
        if collar:
            pts.append([top_r, spout_h + cone_h + collar])
            radii = [0.0, bend, collar_bend, 0.0]
        section, _ = _vessel(_fillet(np.array(pts), radii, closed=False), thickness, edge, open_bottom=True)
        return _revolve_section(section, edge)

    return build


def _hammer(rng: np.random.Generator) -> Builder:
    """A tapered oval handle under a round head with a bevelled face and a cross-peen wedge."""
    handle_len = rng.uniform(95, 150)
    hx, aspect = rng.uniform(6, 9), rng.uniform(1.2, 1.6)  # handle half-width along the head, y/x ratio
    taper, knob = rng.uniform(0.7, 0.95), rng.uniform(1.0, 1.2)
    head_r, face_len, peen_len = rng.uniform(10, 16), rng.uniform(25, 40), rng.uniform(25, 45)
    bevel, peen_w, peen_t = rng.uniform(1.0, 4.0), rng.uniform(0.7, 1.0), rng.uniform(1.5, 3.0)
    head_z = handle_len - 0.4 * head_r

    def build(edge: float) -> mf.Manifold:
        # Handle: rounded knob at the bottom, tapering up into the head (its flat top is hidden there).
        knob_r = hx * knob
        end = _curve(
            lambda s: np.stack([knob_r * np.sin(0.5 * np.pi * s), knob_r * (1 - np.cos(0.5 * np.pi * s))], 1),
            edge,
        )
        handle = np.vstack([end, [[hx * taper, head_z], [0, head_z]]])
        handle = _revolve(handle, edge, aspect=aspect)
        face = np.array([[0, 0.0], [head_r, 0.0], [head_r, face_len], [0, face_len]])
        face = _revolve(_fillet(face, [0, 0, bevel, 0]), edge).rotate((0, 90, 0))  # axis z -> +x
        # Peen: stadium sections from a circle a little inside the face (a small step marks the joint) to
        # a thin wedge, closed by a rounded tip. Outline x (thickness) becomes world z, y stays y.
        s = np.linspace(0, 1, max(2, int(np.ceil(peen_len / edge)) + 1))
        r0 = 0.97 * head_r
        thick, wide = r0 + (peen_t - r0) * s, r0 + (head_r * peen_w - r0) * s
        tip = np.radians(np.arange(_MAX_TURN_DEG, 90.0, _MAX_TURN_DEG))
        stations = np.r_[-3.0, peen_len * s, peen_len + peen_t * np.sin(tip)]
        outlines = [_rounded_rect(t, w, t, edge) for t, w in zip(np.r_[r0, thick], np.r_[r0, wide])]
        outlines += [
            _rounded_rect(peen_t * np.cos(a), wide[-1] * np.cos(a), peen_t * np.cos(a), edge) for a in tip
        ]
        peen = _loft(stations, outlines, end=peen_len + peen_t).rotate((0, -90, 0))
        return handle + (face + peen).translate((0, 0, head_z))

    return build


def _mug(rng: np.random.Generator) -> Builder:
    """A (possibly tapered) cup with a rounded rim and a D-shaped ring handle of oval section."""
    r_bottom, height, thickness = rng.uniform(32, 42), rng.uniform(80, 110), rng.uniform(3.0, 6.0)
    r_top = r_bottom * (1 + rng.uniform(-0.12, 0.12))
    base_edge = rng.uniform(2, 8)
    tube, flat = rng.uniform(4.0, 6.5), rng.uniform(0.6, 1.0)  # tube half-height; radial/half-height
    zc = height * rng.uniform(0.45, 0.55)
    reach_z = min(rng.uniform(10, 18) + tube, min(zc, height - zc) - tube - 6.0)
    reach_x = rng.uniform(8, 15) + tube * flat
    # The inner side of the handle must not fold over itself where the path bends hardest.
    reach_x = max(reach_x, np.sqrt(1.5 * tube * flat * reach_z))
    wall_r = r_bottom + (r_top - r_bottom) * zc / height
    centre_x = wall_r + rng.uniform(0.0, 0.4) * reach_x

    def build(edge: float) -> mf.Manifold:
        outer = _fillet(np.array([[0, 0], [r_bottom, 0], [r_top, height]]), [0, base_edge, 0], closed=False)
        section, mid = _vessel(outer, thickness, edge)
        cup = _revolve_section(section, edge)
        # Handle: a tube of oval section swept along an ellipse in the xz plane, rings even in arc length.
        path = _resample(
            np.stack([reach_x * np.cos(t := np.linspace(0, 2 * np.pi, 721)), reach_z * np.sin(t)], 1),
            edge,
            closed=True,
        )
        after, before = np.roll(path, -1, axis=0), np.roll(path, 1, axis=0)
        tangent = (after - before) / np.linalg.norm(after - before, axis=1, keepdims=True)
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], 1)  # outward for a counter-clockwise path
        phi = 2 * np.pi * (np.arange(_arc_segments(tube, edge)) + 0.5) / _arc_segments(tube, edge)
        across, along_y = tube * flat * np.cos(phi), tube * np.sin(phi)
        rings = [
            np.stack([centre_x + p[0] + n[0] * across, along_y, zc + p[1] + n[1] * across], 1)
            for p, n in zip(path, normal)
        ]
        handle = _manifold(*_tube(rings, closed=True))
        return cup + (handle - _revolve_coarse(mid, r_bottom, edge))

    return build


def _ring(rng: np.random.Generator) -> Builder:
    """A torus whose section is a superellipse: from a round donut to a square-edged washer."""
    half_w = rng.uniform(7, 18)
    half_h = half_w * rng.uniform(0.5, 1.3)
    major = rng.uniform(half_w + 10, half_w + 40)
    exponent = rng.uniform(2.0, 5.0)

    def section(s):
        c, si = np.cos(2 * np.pi * s), np.sin(2 * np.pi * s)
        return np.stack(
            [
                major + half_w * np.sign(c) * np.abs(c) ** (2 / exponent),
                half_h * np.sign(si) * np.abs(si) ** (2 / exponent),
            ],
            1,
        )

    def build(edge: float) -> mf.Manifold:
        # Dense enough that the corners of a square-ish section turn by less than 15 degrees per step.
        return _revolve(_curve(section, edge / 3, n_dense=4000)[:-1], edge, closed=True)

    return build


def _spoon(rng: np.random.Generator) -> Builder:
    """An oval scoop with a rounded rim, and a flat handle that rises from the rim and widens to its end."""
    half_len, depth, thickness = rng.uniform(22, 38), rng.uniform(8, 18), rng.uniform(2.5, 3.5)
    aspect = rng.uniform(0.55, 0.8)
    length, rise = rng.uniform(60, 110), rng.uniform(5, 20)
    th = rng.uniform(1.2, 2.0)  # half thickness of the handle
    w_start, w_end = rng.uniform(4, 7), rng.uniform(8, 13)

    def scoop(s):
        psi = 0.5 * np.pi * s
        return np.stack([half_len * np.sin(psi), depth * (1 - np.cos(psi))], axis=1)

    def build(edge: float) -> mf.Manifold:
        section, mid = _vessel(_curve(scoop, edge / 2), thickness, edge)
        wall = _revolve_section(section, edge).scale((1, aspect, 1))
        mid = _revolve_coarse(mid, half_len, edge).scale((1, aspect, 1))
        # Handle: stadium sections (thickness 2 th along outline x, which becomes world z; width 2 w),
        # widening towards a rounded end; its flat start is hidden in the rim and trimmed at mid-wall.
        straight = length - w_end
        s = np.linspace(0, 1, max(2, int(np.ceil(straight / edge)) + 1))
        cap = np.radians(np.arange(_MAX_TURN_DEG, 90.0, _MAX_TURN_DEG / 2))
        stations = np.r_[-thickness, straight * s, straight + w_end * np.sin(cap)]
        widths = np.r_[w_start, w_start + (w_end - w_start) * s**2, w_end * np.cos(cap)]
        outlines = [_rounded_rect(min(th, w), w, th, edge) for w in widths]
        handle = _loft(stations, outlines, end=length).rotate((0, 90 - rise, 0))
        # Its top a little below the rim's top: meeting the rounded rim tangentially makes near-degenerate
        # intersections (Open3D found self-intersecting triangles there).
        handle = handle.translate((half_len - thickness / 2, 0, depth - th - 0.25 * thickness))
        return wall + (handle - mid)

    return build


def _wineglass(rng: np.random.Generator) -> Builder:
    """A stemmed glass: power-law bowl (sometimes closing in, like a tulip), stem, and a flat foot."""
    bowl_r, bowl_h, power = rng.uniform(30, 42), rng.uniform(45, 75), rng.uniform(1.8, 3.0)
    belly = rng.uniform(0.55, 1.0)  # fraction of the bowl height where it is widest
    rim_r = bowl_r * rng.uniform(0.8, 1.0)
    thickness = rng.uniform(2.0, 3.5)
    stem_r, stem_h = rng.uniform(3.5, 6.0), rng.uniform(30, 60)
    foot_r, foot_t = rng.uniform(28, 38), rng.uniform(3, 5)

    def lower_z(r):  # flat at the bottom, vertical where widest: no crease where the upper part starts
        return belly * bowl_h * (1 - np.sqrt(np.clip(1 - (r / bowl_r) ** power, 0.0, 1.0)))

    def lower(s):
        return np.stack([bowl_r * s, lower_z(bowl_r * s)], axis=1)

    def upper(s):
        r = bowl_r + (rim_r - bowl_r) * (1 - np.cos(0.5 * np.pi * s))
        return np.stack([r, bowl_h * (belly + (1 - belly) * s)], 1)

    def build(edge: float) -> mf.Manifold:
        outer = _curve(lower, edge / 2)
        if belly < 1.0:
            outer = np.vstack([outer, _curve(upper, edge / 2)[1:]])
        z0 = foot_t + stem_h
        bowl, _ = _vessel(outer, thickness, edge)
        flare_r = 2.0 * stem_r
        flare_z = z0 + lower_z(flare_r) + thickness / 2
        stem = np.array(
            [
                [0, 0],
                [foot_r, 0],
                [foot_r, foot_t * 0.6],
                [stem_r + 6, foot_t + 2],
                [stem_r, foot_t + 10],
                [stem_r, z0 - 6],
                [flare_r, flare_z],
                [0, z0 + thickness / 2],
            ]
        )
        stem = _section(_mirror(_fillet(stem, [0, 0.8, foot_t * 0.3, 3.0, 4.0, 4.0, 0, 0])))
        return _revolve_section(_close(bowl.translate((0, z0)) + stem, 2.0, edge), edge)

    return build


_CLASS_BUILDERS: dict[str, Callable[[np.random.Generator], Builder]] = {
    "bottle": _bottle,
    "bowl": _bowl,
    "box": _box,
    "can": _can,
    "funnel": _funnel,
    "hammer": _hammer,
    "mug": _mug,
    "ring": _ring,
    "spoon": _spoon,
    "wineglass": _wineglass,
}

#: The built-in object classes, in a fixed order.
CLASSES: tuple[str, ...] = tuple(_CLASS_BUILDERS)


# -------------------------------------------------------------------------------------------- public API
def _closed_and_oriented(triangles: np.ndarray, n_vertices: int) -> bool:
    """Every edge in exactly two triangles, every directed edge once (same test as ``is_watertight``)."""
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    keys = directed[:, 0] * n_vertices + directed[:, 1]
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n_vertices + undirected[:, 1], return_counts=True)
    return bool(np.all(counts == 2)) and len(np.unique(keys)) == len(keys)


def _collapse_tiny_edges(
    vertices: np.ndarray, triangles: np.ndarray, tol_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Merge the end points of edges shorter than ``tol_mm`` and drop the triangles that vanish.

    Booleans where parts meet almost tangentially can leave needle triangles with a sub-micrometre edge,
    which Open3D reports as self-intersecting. The mesh is returned unchanged if there are none, or if
    merging would leave it not closed and consistently oriented.
    """
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    short = directed[np.linalg.norm(vertices[directed[:, 0]] - vertices[directed[:, 1]], axis=1) < tol_mm]
    if len(short) == 0:
        return vertices, triangles
    parent = np.arange(len(vertices))
    for a, b in short:  # a handful at most: a plain union-find
        while parent[a] != a:
            a = parent[a]
        while parent[b] != b:
            b = parent[b]
        parent[max(a, b)] = min(a, b)
    while np.any(parent[parent] != parent):
        parent = parent[parent]
    merged = parent[triangles]
    merged = merged[
        (merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2]) & (merged[:, 2] != merged[:, 0])
    ]
    used, inverse = np.unique(merged, return_inverse=True)
    merged = inverse.reshape(-1, 3)
    if not _closed_and_oriented(merged, len(used)):
        return vertices, triangles
    return vertices[used], merged


def _scale_to_build_size(solid: mf.Manifold, name: str) -> float:
    """The factor that brings ``solid`` to the build size (:attr:`ObjectModel.size`: the diameter of the
    sphere about its surface centroid that holds it); a failed construction raises."""
    if solid.status() != mf.Error.NoError or solid.is_empty():
        raise InvalidMeshError(f"{name}: construction failed ({solid.status()})")
    mesh = solid.to_mesh64()
    vertices = np.asarray(mesh.vert_properties)[:, :3]
    center = surface_centroid(vertices, np.asarray(mesh.tri_verts, dtype=np.int64))
    return _BUILD_MM / (2.0 * float(np.linalg.norm(vertices - center, axis=1).max()))


def make_object(
    class_name: str, seed: int | np.random.Generator = 0, *, size_mm: float = DEFAULT_SIZE_MM
) -> ObjectModel:
    """One watertight, outward-oriented instance of ``class_name``, drawn from ``seed``.

    The instance is centred on its surface centroid and scaled to ``size_mm`` (mm), the diameter of the sphere
    about that centre holding it (:func:`perception.geometry.normalize`); it stands upright (+z), the
    class's canonical pose (turn it with :func:`perception.geometry.rotate` for any other). Same integer seed -> identical vertex bytes; the name is ``"class/seed"`` (or
    ``"class/rng"`` when a ``numpy.random.Generator`` is given), the label the class name.

    Raises:
        DatasetError: unknown class (the message lists the classes), or a seed that is neither a
            non-negative integer nor a generator.
        InvalidArgumentError: ``size_mm`` is not a positive number. InvalidMeshError: the construction failed.
    """
    if class_name not in _CLASS_BUILDERS:
        raise DatasetError(
            f"unknown object class {class_name!r}; the built-in classes are {', '.join(CLASSES)}"
        )
    if isinstance(seed, np.random.Generator):
        rng, name = seed, f"{class_name}/rng"
    elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0:
        # Mixing in the class name gives each class its own stream for the same seed.
        rng, name = (
            np.random.default_rng([int(seed), zlib.crc32(class_name.encode())]),
            f"{class_name}/{int(seed)}",
        )
    else:
        raise DatasetError(
            f"{class_name}: seed must be a non-negative integer or a numpy Generator, got {seed!r}"
        )
    if not (isinstance(size_mm, (int, float, np.number)) and np.isfinite(size_mm) and size_mm > 0):
        raise InvalidArgumentError(f"{name}: size_mm must be a positive number of millimetres, got {size_mm!r}")
    build = _CLASS_BUILDERS[class_name](rng)
    # A coarse draft gives the scale and area; the edge length follows from them (in final mm).
    draft = build(8.0)
    scale = _scale_to_build_size(draft, name)
    area_mm2 = draft.surface_area() * scale**2
    edge = float(np.clip(np.sqrt(4 * area_mm2 / (np.sqrt(3) * TARGET_TRIANGLES)), *EDGE_RANGE_MM))
    solid = build(edge / scale)
    scale = _scale_to_build_size(solid, name)
    mesh = solid.scale((scale, scale, scale)).simplify(_TINY_EDGE_MM).to_mesh64()
    vertices, triangles = _collapse_tiny_edges(
        np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts, dtype=np.int64), _TINY_EDGE_MM
    )
    vertices, transform = normalize(vertices, size_mm, triangles=triangles)
    transform[:3, :3] *= scale  # from the construction frame, not only from the build size
    log.debug("%s: %d triangles, edge %.2f mm at 150 mm", name, len(mesh.tri_verts), edge)
    return ObjectModel(vertices, triangles.astype(np.int32), name=name, label=class_name, transform=transform)


def make_dataset(
    n_per_class: int,
    seed: int = 0,
    *,
    classes: tuple[str, ...] | list[str] = CLASSES,
    size_mm: float = DEFAULT_SIZE_MM,
    progress: bool = False,
) -> list[ObjectModel]:
    """``n_per_class`` instances of every class, with seeds ``seed .. seed + n_per_class - 1``.

    Objects come class by class; each can be rebuilt alone with ``make_object(class, seed)`` from its name.

    Raises:
        DatasetError: an unknown class or a negative ``n_per_class``.
    """
    if n_per_class < 0:
        raise InvalidArgumentError(f"n_per_class must be >= 0, got {n_per_class}")
    jobs = [(c, seed + i) for c in classes for i in range(n_per_class)]
    return [
        make_object(c, s, size_mm=size_mm)
        for c, s in progress_bar(jobs, enabled=progress, desc="objects", unit="obj")
    ]


def _shade(model: ObjectModel, direction: np.ndarray, pixels: int) -> np.ndarray:
    """Lambert-shaded orthographic view along ``direction`` (pixels x pixels, values in [0, 1], NaN for
    background), lit from above-left of the camera rather than by a headlight, so shapes read as 3D."""
    from perception.render import render_views

    view = render_views(
        model, width=pixels, height=pixels, directions=-np.asarray(direction, dtype=np.float64)[None]
    )[0]
    cam = view.camera
    light = -cam.forward + 0.6 * cam.up + 0.4 * cam.right
    light /= np.linalg.norm(light)
    # The view's normals are interpolated, so the figure shows the surface rather than the tessellation.
    return np.where(view.mask, 0.2 + 0.8 * np.clip(view.normal @ light, 0.0, 1.0), np.nan)


def catalogue_figure(
    path: str | Path, seed: int = 0, *, pixels: int = 240, models: list[ObjectModel] | None = None
) -> Path:
    """Write a PNG sheet with one shaded instance of every class (seed ``seed``) to ``path``; return it.

    ``models`` (one per class, in :data:`CLASSES` order) reuses objects the caller already built.

    Rendering is Open3D ray casting (no OpenGL), the sheet matplotlib (Agg). The file is written
    atomically (temporary file, then rename).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = 5
    if models is None:
        models = [make_object(class_name, seed) for class_name in CLASSES]
    rows = int(np.ceil(len(models) / cols))
    fig = Figure(figsize=(2.4 * cols, 2.6 * rows), dpi=100)
    FigureCanvasAgg(fig)
    direction = np.array([-1.0, 1.4, -0.9])
    for i, model in enumerate(models):
        ax = fig.add_subplot(rows, cols, i + 1)
        ax.imshow(_shade(model, direction, pixels), cmap="gray", vmin=0, vmax=1, interpolation="bilinear")
        ax.set_title(f"{model.name}  ({model.n_triangles} tri)", fontsize=9)
        ax.set_axis_off()
    fig.tight_layout()
    save_figure(fig, path, format="png")
    log.info("wrote the catalogue sheet %s", path)
    return path
