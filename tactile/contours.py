"""Contours: exact plane sections of a mesh, chained into polylines, resampled to probes with poses.

A contour is what a finger would follow: the plane through the object centre and two chosen points cuts
the surface, the outer loop of that cut is resampled at equal arc length, and each probe gets a pose
(position on the surface, outward normal interpolated over its triangle, tangent along the contour).

The section is exact and vectorised: every intersection point is identified by the mesh vertex it
coincides with or the mesh edge it lies on, so segments from neighbouring triangles share endpoint ids
and chaining needs no distance tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import ObjectModel

#: Vertices closer to the plane than this fraction of the object size count as lying on it.
ON_PLANE_TOLERANCE = 1e-9
#: Plane points lie within this distance of the origin, mm (far beyond any object; squares stay finite).
MAX_PLANE_POINT_MM = 1e150


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of (..., 3) arrays (same formula, same bits) without its set-up cost, which dominates
    on the 3-vectors and short batches of a contour."""
    i, j = [1, 2, 0], [2, 0, 1]
    return a[..., i] * b[..., j] - a[..., j] * b[..., i]


def _shifted(a: np.ndarray, k: int = 1) -> np.ndarray:
    """``np.roll(a, -k, axis=0)`` (row k first, cyclically; 0 <= k < len(a)) without np.roll's set-up cost."""
    return np.concatenate((a[k:], a[:k]))


@dataclass(frozen=True, eq=False)
class Plane:
    """A cutting plane: a ``point`` on it (3,) mm and a unit ``normal`` (3,).

    The normal is scaled by its largest component before normalising, so any finite non-zero normal works
    (1e308 or 1e-300 alike).

    Raises:
        ContourError: non-finite or badly shaped arrays, a zero normal, or a point further than
            ``MAX_PLANE_POINT_MM`` from the origin (signed distances would overflow).
    """

    point: np.ndarray
    normal: np.ndarray

    def __post_init__(self) -> None:
        point = np.asarray(self.point, dtype=np.float64)
        normal = np.asarray(self.normal, dtype=np.float64)
        if point.shape != (3,) or normal.shape != (3,):
            raise InvalidArgumentError(f"plane point and normal must be 3-vectors, got {point.shape}, {normal.shape}")
        if not (np.isfinite(point).all() and np.isfinite(normal).all()):
            raise ContourError(f"plane has a non-finite point {point} or normal {normal}")
        if np.abs(point).max() > MAX_PLANE_POINT_MM:
            raise ContourError(
                f"plane point {point} lies further than {MAX_PLANE_POINT_MM:g} mm from the origin; "
                "distances to it overflow"
            )
        largest = np.abs(normal).max()
        if largest == 0:
            raise ContourError(f"plane normal {normal} has zero length")
        scaled = normal / largest  # largest component +-1: the norm below neither overflows nor underflows
        object.__setattr__(self, "point", point)
        object.__setattr__(self, "normal", scaled / np.linalg.norm(scaled))

    def basis(self) -> tuple[np.ndarray, np.ndarray]:
        """Two unit in-plane axes (u, v) with u x v = normal; u is fixed by the normal alone."""
        if "_basis" not in self.__dict__:  # computed once: every loop of a section asks for it
            axis = np.eye(3)[np.argmin(np.abs(self.normal))]
            u = _cross(self.normal, axis)
            u /= np.linalg.norm(u)
            object.__setattr__(self, "_basis", (u, _cross(self.normal, u)))
        return self._basis

    def to_dict(self) -> dict:
        """JSON-able form (lists of floats, mm)."""
        return {"point": self.point.tolist(), "normal": self.normal.tolist()}


def plane_through(center, p1, p2, *, min_sine: float = 1e-3) -> Plane:
    """The plane through ``center`` and points ``p1``, ``p2`` (mm), normal (p1 - c) x (p2 - c) normalised.

    Raises:
        ContourError: a point coincides with the centre, the three are near-collinear
            (|sin angle| < ``min_sine``), or an input is not a finite 3-vector.
    """
    c, a, b = (np.asarray(x, dtype=np.float64) for x in (center, p1, p2))
    if not all(x.shape == (3,) and np.isfinite(x).all() for x in (c, a, b)):
        raise ContourError(f"plane_through needs three finite 3-vectors, got {center!r}, {p1!r}, {p2!r}")
    # Halves first (a - c overflows for +-1e308), then unit directions, so the cross product stays finite.
    da, db = 0.5 * a - 0.5 * c, 0.5 * b - 0.5 * c
    if not (np.abs(da).max() > 0 and np.abs(db).max() > 0):
        raise ContourError(f"a point given to plane_through coincides with the centre {c}: no plane")
    ua, ub = (x / np.abs(x).max() for x in (da, db))
    ua, ub = ua / np.linalg.norm(ua), ub / np.linalg.norm(ub)
    cross = _cross(ua, ub)
    sine = np.linalg.norm(cross)
    if not sine >= min_sine:
        raise ContourError(
            f"points {a}, {b} are near-collinear with the centre {c} (|sin| = {sine:.2e} < {min_sine}); "
            "draw other points"
        )
    return Plane(c, cross)


@dataclass(frozen=True, eq=False)
class Chain:
    """One polyline of a section: ``points`` (M, 3) mm, ``closed`` (first point not repeated), and
    ``triangle_ids`` (M,) for closed loops or (M - 1,) for open chains: the triangle holding segment k
    (points k -> k + 1, the last closing segment included for loops)."""

    points: np.ndarray
    closed: bool
    triangle_ids: np.ndarray

    @property
    def segment_ends(self) -> np.ndarray:
        """(S, 3) end point of each segment (start points are ``points[:S]``)."""
        return _shifted(self.points) if self.closed else self.points[1:]

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(self.segment_ends - self.points[: len(self.triangle_ids)], axis=1).sum())


def _signed_distances(model: ObjectModel, plane: Plane) -> np.ndarray:
    d = (model.vertices - plane.point) @ plane.normal
    d[np.abs(d) <= ON_PLANE_TOLERANCE * max(model.size, 1e-12)] = 0.0
    return d


def _segments(model: ObjectModel, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The section's points as sorted point ids (P,), its unique segments as (S, 2) indices into them, and
    the triangle of each segment (S,).

    Point id v < V is vertex v (on the plane); id V + a * V + b (a < b) is the crossing on edge (a, b).
    A triangle gives a segment when exactly two of its vertices/edges meet the plane: two crossed edges,
    an on-plane vertex and the opposite crossed edge, or an edge lying in the plane. Coplanar faces give
    none (their boundary edges come from the neighbours) and an in-plane edge, seen by both its
    triangles, is kept once.
    """
    n_vertices = len(model.vertices)
    dt = np.take(d, model.triangles)
    # One pass over all triangles keeps those touching the plane; the rest of the work is on those few.
    lo = np.minimum(np.minimum(dt[:, 0], dt[:, 1]), dt[:, 2])
    hi = np.maximum(np.maximum(dt[:, 0], dt[:, 1]), dt[:, 2])
    tri_ids = np.flatnonzero((lo <= 0) & (hi >= 0) & ((lo < 0) | (hi > 0)))
    tri = model.triangles[tri_ids].astype(np.int64)
    side = np.sign(dt[tri_ids]).astype(np.int8)
    ids = np.full((len(tri_ids), 6), -1, dtype=np.int64)
    ids[:, :3] = np.where(side == 0, tri, -1)
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        lo_v, hi_v = np.minimum(tri[:, i], tri[:, j]), np.maximum(tri[:, i], tri[:, j])
        crossed = side[:, i] * side[:, j] < 0
        ids[:, 3 + k] = np.where(crossed, n_vertices + lo_v * n_vertices + hi_v, -1)
    keep = (ids >= 0).sum(axis=1) == 2
    # The two valid ids are the two largest in the row (invalid ones are -1).
    pairs = np.sort(ids[keep], axis=1)[:, -2:]
    # Rows as 1-D keys of compact ids: np.unique on keys is far cheaper than on rows (axis=0).
    nodes, compact = np.unique(pairs, return_inverse=True)
    compact = compact.reshape(-1, 2)
    _, first = np.unique(compact[:, 0] * len(nodes) + compact[:, 1], return_index=True)
    return nodes, compact[first], tri_ids[keep][first]


def _point_coordinates(model: ObjectModel, d: np.ndarray, ids: np.ndarray) -> np.ndarray:
    n_vertices = len(model.vertices)
    points = np.empty((len(ids), 3))
    on_vertex = ids < n_vertices
    points[on_vertex] = model.vertices[ids[on_vertex]]
    edge = ids[~on_vertex] - n_vertices
    a, b = edge // n_vertices, edge % n_vertices
    # d[a] and d[b] have strictly opposite signs here, so the denominator is never zero.
    t = d[a] / (d[a] - d[b])
    points[~on_vertex] = model.vertices[a] + t[:, None] * (model.vertices[b] - model.vertices[a])
    return points


def _walk(edges: np.ndarray, n_nodes: int) -> list[tuple[list[int], list[int], bool]]:
    """Chain undirected edges into (node list, edge list, closed) walks, open chains first."""
    degree = np.bincount(edges.ravel(), minlength=n_nodes)
    if (degree == 2).all():
        return _walk_loops(edges, n_nodes)
    adjacency: list[list[int]] = [[] for _ in range(n_nodes)]
    for e, (a, b) in enumerate(edges.tolist()):
        adjacency[a].append(e)
        adjacency[b].append(e)
    used = [False] * len(edges)
    cursor = [0] * n_nodes
    endpoints = edges.tolist()

    def next_edge(node: int) -> int:
        incident = adjacency[node]
        while cursor[node] < len(incident) and used[incident[cursor[node]]]:
            cursor[node] += 1
        return incident[cursor[node]] if cursor[node] < len(incident) else -1

    # True ends (one edge) first: a walk from an end runs on through a branch node instead of stopping there.
    odd = sorted(np.flatnonzero(degree % 2).tolist(), key=lambda n: degree[n] != 1)
    walks = []
    for start in odd + list(range(n_nodes)):
        while (edge := next_edge(start)) >= 0:
            nodes, path, node = [start], [], start
            while edge >= 0:
                used[edge] = True
                path.append(edge)
                a, b = endpoints[edge]
                node = b if a == node else a
                nodes.append(node)
                edge = next_edge(node)
            closed = node == start and len(path) >= 3
            walks.append((nodes[:-1] if closed else nodes, path, closed))
    return walks


def _walk_loops(edges: np.ndarray, n_nodes: int) -> list[tuple[list[int], list[int], bool]]:
    """:func:`_walk` when every node has two edges (the section of a closed manifold): disjoint loops, each from
    its first unused edge ``(a, b)``, a to b first (the usual case, so its step is lean: the other edge at a node
    is the sum of its two edges less the one it came by, the next node the sum of the edge's ends less this one)."""
    incident = (np.argsort(edges.ravel(), kind="stable") // 2).reshape(n_nodes, 2)
    other_edge = incident.sum(axis=1).tolist()
    other_end = edges.sum(axis=1).tolist()
    used = np.zeros(len(edges), dtype=bool)
    walks = []
    first = 0
    while True:
        start, node = edges[first].tolist()
        nodes, path, edge = [start], [first], first
        while node != start:
            nodes.append(node)
            edge = other_edge[node] - edge
            path.append(edge)
            node = other_end[edge] - node
        walks.append((nodes, path, True))  # segments are unique, so a loop has >= 3
        used[path] = True
        first = int(np.argmin(used))
        if used[first]:
            return walks


def section_chains(model: ObjectModel, plane: Plane) -> list[Chain]:
    """The exact section of ``model`` by ``plane`` as chained polylines (see :class:`Chain`).

    Closed meshes give closed loops; open meshes and soups may also give open chains (ending at the
    boundary). A plane that only touches the mesh at isolated vertices gives nothing.
    """
    d = _signed_distances(model, plane)
    ids, edges, seg_tris = _segments(model, d)
    if len(edges) == 0:
        return []
    points = _point_coordinates(model, d, ids)
    chains = []
    tolerance = ON_PLANE_TOLERANCE * max(model.size, 1e-12)
    for nodes, path, closed in _walk(edges, len(ids)):
        if not closed and len(path) >= 3 and np.linalg.norm(points[nodes[-1]] - points[nodes[0]]) <= tolerance:
            nodes, closed = nodes[:-1], True  # both ends on one spot: a loop cut open by a crack (T-junction)
        chains.append(Chain(points[nodes], closed, seg_tris[path]))
    return chains


def section(model: ObjectModel, plane: Plane) -> list[np.ndarray]:
    """The exact section of ``model`` by ``plane``: a list of (M, 3) polylines, mm.

    Closed loops do not repeat their first point; :func:`section_chains` gives the closed flag and the
    triangle of every segment.
    """
    return [chain.points for chain in section_chains(model, plane)]


def signed_area(points: np.ndarray, plane: Plane) -> float:
    """Signed area (mm^2) enclosed by a closed polyline, counter-clockwise about the plane normal > 0."""
    u, v = plane.basis()
    relative = points - plane.point
    x, y = relative @ u, relative @ v
    return 0.5 * float(np.sum(x * _shifted(y) - _shifted(x) * y))


def interpolate_normals(model: ObjectModel, points: np.ndarray, triangle_ids: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals at surface ``points`` (mm): barycentric blend of their triangle's vertex normals.

    Points are projected into their triangle (barycentric weights clipped to >= 0). Where the blend
    cancels, the face normal is used, then the first vertex normal, so the result is always finite.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = model.triangles[np.asarray(triangle_ids)]
    a, b, c = (model.vertices[tri[:, i]] for i in range(3))
    e0, e1, ep = b - a, c - a, points - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((e0, e0), (e0, e1), (e1, e1)))
    d20, d21 = np.einsum("ij,ij->i", ep, e0), np.einsum("ij,ij->i", ep, e1)
    denom = d00 * d11 - d01 * d01
    ok = denom > 1e-300
    with np.errstate(divide="ignore", invalid="ignore"):
        w1 = np.where(ok, (d11 * d20 - d01 * d21) / np.where(ok, denom, 1.0), 1 / 3)
        w2 = np.where(ok, (d00 * d21 - d01 * d20) / np.where(ok, denom, 1.0), 1 / 3)
    weights = np.clip(np.stack([1 - w1 - w2, w1, w2], axis=1), 0.0, None)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-300)
    vn = model.vertex_normals[tri]  # (N, 3 vertices, 3)
    normals = np.einsum("nk,nkj->nj", weights, vn)
    length = np.linalg.norm(normals, axis=1)
    bad = length < 1e-9
    if bad.any():
        face = model.triangle_normals[np.asarray(triangle_ids)[bad]]
        face_bad = np.linalg.norm(face, axis=1) < 0.5
        face[face_bad] = vn[bad][face_bad, 0]
        normals[bad] = face
        length[bad] = np.linalg.norm(face, axis=1)
    return normals / length[:, None]


def orthonormal_tangents(
    normals: np.ndarray, directions: np.ndarray, fallback_axis: np.ndarray
) -> np.ndarray:
    """Unit tangents: ``directions`` made orthogonal to unit ``normals``; degenerate rows use
    ``fallback_axis`` x normal, then any axis perpendicular to the normal."""
    t = directions - np.einsum("ij,ij->i", directions, normals)[:, None] * normals
    length = np.linalg.norm(t, axis=1)
    bad = length < 1e-9 * np.maximum(np.linalg.norm(directions, axis=1), 1e-300)
    if bad.any():
        alt = np.cross(np.broadcast_to(fallback_axis, normals[bad].shape), normals[bad])
        still = np.linalg.norm(alt, axis=1) < 1e-9
        axes = np.eye(3)[np.argmin(np.abs(normals[bad]), axis=1)]
        alt[still] = np.cross(normals[bad][still], axes[still])
        t[bad] = alt
        length[bad] = np.linalg.norm(alt, axis=1)
    return t / length[:, None]


@dataclass(frozen=True, eq=False)
class Contour:
    """A contour with N probe poses (mm, unit vectors), ready for the tactile sensor.

    Attributes:
        plane: the cutting plane.
        polyline: (M, 3) the chosen loop (or chain), mm, counter-clockwise about the plane normal for loops.
        closed: whether ``polyline`` is a closed loop (first point not repeated).
        positions: (N, 3) probe positions on the surface, mm.
        normals: (N, 3) unit outward surface normals at the probes (vertex normals blended over the triangle).
        tangents: (N, 3) unit tangents along the contour, orthogonal to the normals (pad x axis).
        triangle_ids: (N,) triangle each probe lies on.
    """

    plane: Plane
    polyline: np.ndarray
    closed: bool
    positions: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    triangle_ids: np.ndarray

    @property
    def binormals(self) -> np.ndarray:
        """(N, 3) normals x tangents: the pad y axis."""
        return np.cross(self.normals, self.tangents)

    @property
    def n_probes(self) -> int:
        return len(self.positions)

    @property
    def length_mm(self) -> float:
        """Length of the polyline, mm (closing segment included for loops)."""
        ends = _shifted(self.polyline) if self.closed else self.polyline[1:]
        return float(np.linalg.norm(ends - self.polyline[: len(ends)], axis=1).sum())


def choose_chain(chains: list[Chain], plane: Plane) -> Chain:
    """The outer loop: the closed loop with the largest enclosed area in the plane.

    Several loops (handles, separate parts) -> the one enclosing the most area, which is the outer
    silhouette of the cut; holes and small islands are ignored. Only open chains (open meshes, soups)
    -> the longest chain. A chosen loop is oriented counter-clockwise about the plane normal.
    """
    loops = [c for c in chains if c.closed]
    if not loops:
        return max(chains, key=lambda c: c.length_mm)
    areas = [signed_area(c.points, plane) for c in loops]
    best = int(np.argmax(np.abs(areas)))
    loop = loops[best]
    if areas[best] < 0:
        # Reversed node order: segment k now runs between old nodes m-1-k and m-2-k.
        loop = Chain(loop.points[::-1].copy(), True, _shifted(loop.triangle_ids[::-1]))
    return loop


#: Loop points within this relative distance of the furthest one tie for the start (symmetric objects).
START_TIE_TOLERANCE = 1e-9


def _furthest_start(points: np.ndarray, center: np.ndarray) -> int:
    """Index of the loop point furthest from ``center``. Symmetric objects tie (a bottle cut through its axis
    has two furthest corners, mirror images): then the tied point after the longest stretch of loop from the
    previous tied point wins, which rotation, scale and rounding do not change. Exact n-fold ties (a circle)
    give the first; any is then the same contour up to the symmetry."""
    distance = np.linalg.norm(points - center, axis=1)
    tied = np.flatnonzero(distance >= distance.max() * (1 - START_TIE_TOLERANCE))
    if len(tied) == 1:
        return int(tied[0])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(_shifted(points) - points, axis=1))])
    at, total = arc[tied], arc[-1]
    gaps = np.diff(np.concatenate([[at[-1] - total], at]))
    best = gaps >= gaps.max() * (1 - START_TIE_TOLERANCE)
    return int(tied[np.argmax(best)])


def make_contour(model: ObjectModel, plane: Plane, n_probes: int = 25, *, start=None) -> Contour:
    """Cut ``model`` with ``plane``, keep the outer loop (:func:`choose_chain`) and place ``n_probes``
    probes at equal arc length along it, with poses.

    Loops start at the loop point nearest ``start`` (mm), by default at the point furthest from the plane's
    point (the object centre), so the result depends neither on chaining order nor on the object's pose
    (turning the object and the plane together turns the probes with them); open chains run from one end to
    the other, both ends included.

    Raises:
        ContourError: the plane misses the object, ``n_probes`` < 2, or the cut has zero length.
    """
    if int(n_probes) != n_probes or n_probes < 2:
        raise InvalidArgumentError(f"{model.name}: n_probes must be an integer >= 2, got {n_probes!r}")
    n_probes = int(n_probes)
    chains = section_chains(model, plane)
    if not chains:
        in_plane = int((_signed_distances(model, plane)[model.triangles] == 0).all(axis=1).sum())
        if in_plane:
            raise ContourError(
                f"{model.name}: the plane with normal {plane.normal.round(4).tolist()} contains {in_plane} of "
                "the object's triangles and crosses none (it lies in a flat face): no section to follow"
            )
        raise ContourError(
            f"{model.name}: the plane through {plane.point.round(3).tolist()} with normal "
            f"{plane.normal.round(4).tolist()} misses the object (no section)"
        )
    chain = choose_chain(chains, plane)
    points, tris = chain.points, chain.triangle_ids
    if chain.closed:
        if start is None:
            first = _furthest_start(points, plane.point)
        else:
            first = int(np.argmin(np.linalg.norm(points - np.asarray(start, dtype=np.float64), axis=1)))
        points, tris = _shifted(points, first), _shifted(tris, first)
        ends = _shifted(points)
    else:
        ends = points[1:]
    starts = points[: len(ends)]
    seg = ends - starts
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]
    if not total > 0:
        raise ContourError(f"{model.name}: the section by this plane has zero length (plane only touches it)")
    arc = total * np.arange(n_probes) / (n_probes if chain.closed else n_probes - 1)
    k = np.clip(np.searchsorted(cum, arc, side="right") - 1, 0, len(seg) - 1)
    frac = np.clip(np.divide(arc - cum[k], seg_len[k], out=np.zeros(n_probes), where=seg_len[k] > 0), 0, 1)
    positions = starts[k] + frac[:, None] * seg[k]
    triangle_ids = tris[k]
    normals = interpolate_normals(model, positions, triangle_ids)
    # Along the segment where it has length, else along the plane: n_plane x normal is tangent to the cut.
    directions = np.where(seg_len[k, None] > 0, seg[k], _cross(plane.normal, normals))
    tangents = orthonormal_tangents(normals, directions, plane.normal)
    return Contour(plane, points, chain.closed, positions, normals, tangents, triangle_ids)


__all__ = [
    "Chain",
    "Contour",
    "Plane",
    "choose_chain",
    "interpolate_normals",
    "make_contour",
    "orthonormal_tangents",
    "plane_through",
    "section",
    "section_chains",
    "signed_area",
]
