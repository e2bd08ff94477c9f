"""Consistent, outward triangle winding for loaded meshes.

Everything downstream trusts the winding: vertex normals, the sign of the mean curvature, the FSR pad
(which lies on the outward side and shrinks where the surface pokes through it). A file wound inward loads
fine but gives normals pointing into the object, so :func:`orient_outward` fixes it on load:

1. Consistency: over edges shared by exactly two triangles, neighbours must traverse the edge in opposite
   directions. Each edge-connected patch is made consistent from one seed triangle (flip parity propagated
   along a spanning tree). A patch that cannot be made consistent (Moebius-like) is left as it is, with a
   warning.
2. Outward: a closed patch (no boundary edge) is outward when its signed volume is positive, or negative
   for a patch nested inside an odd number of other closed patches (an inner wall around a cavity; nesting
   from the generalised winding number). An open patch is outward when its area-weighted normals point away
   from its centroid (the flux of x - centroid, the signed volume of an open surface); where that vote is
   too small to call (a flat plate), the patch keeps its winding.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

log = logging.getLogger(__name__)

#: An open patch whose normal vote |flux| is below this fraction of its area x size is left as it is.
OPEN_VOTE_TOLERANCE = 1e-3
#: Closed patches beyond this count are not tested for nesting (cost grows with their square).
MAX_NESTING_PATCHES = 200
#: Open patches are voted on by rays from this many directions, on grids of this many pixels a side.
VISIBILITY_VIEWS = 40
VISIBILITY_PIXELS = 48


@dataclass(frozen=True)
class OrientationReport:
    """What :func:`orient_outward` did: patch counts and how many triangles it flipped."""

    n_patches: int
    n_closed: int
    n_flipped: int
    non_orientable: int
    undecided: int


def _patches(triangles: np.ndarray):
    """Edge-connected patches over manifold edges, with the flip parity that makes each consistent.

    Returns (labels (F,), flip (F,) bool, conflicts (F,) bool: triangles on an edge still inconsistent
    after flipping, boundary (F,) int: boundary-edge count per triangle).
    """
    n_faces = len(triangles)
    t = triangles.astype(np.int64)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    face = np.tile(np.arange(n_faces), 3)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    n_vertices = int(t.max()) + 1
    key = lo * n_vertices + hi
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
    counts = np.diff(np.r_[starts, len(key_sorted)])
    boundary = np.bincount(face[order[starts[counts == 1]]], minlength=n_faces)
    pair = starts[counts == 2]
    a, b = order[pair], order[pair + 1]
    fa, fb = face[a], face[b]
    # Same direction along the shared edge (both lo->hi or both hi->lo): one of them must flip.
    relative = (directed[a, 0] == directed[b, 0]).astype(np.int8)
    graph = sparse.coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(n_faces, n_faces)).tocsr()
    n_labels, labels = csgraph.connected_components(graph, directed=False)
    if not relative.any():  # already consistent (the usual file): nothing to propagate
        return labels, n_labels, np.zeros(n_faces, dtype=bool), np.zeros(n_faces, dtype=bool), boundary
    # One spanning forest for all patches: a virtual node n_faces joined to every patch's first triangle.
    # Parity of a tree edge = whether the two triangles disagree; pairs sharing two edges count once (a
    # disagreement between those two edges shows up as a conflict below).
    roots = np.unique(labels, return_index=True)[1]
    pair_key = np.minimum(fa, fb) * n_faces + np.maximum(fa, fb)
    unique_keys, first = np.unique(pair_key, return_index=True)
    urel = relative[first]
    src = np.r_[fa, fb, np.full(len(roots), n_faces)]
    dst = np.r_[fb, fa, roots]
    forest = sparse.coo_matrix((np.ones(len(src)), (src, dst)), shape=(n_faces + 1, n_faces + 1)).tocsr()
    nodes, pred = csgraph.breadth_first_order(forest, n_faces, directed=True, return_predecessors=True)
    child = nodes[1:]
    up = pred[child]
    tree = up != n_faces
    child, up = child[tree], up[tree]
    parent = np.arange(n_faces)
    parent[child] = up
    parity = np.zeros(n_faces, dtype=np.int8)
    parity[child] = urel[np.searchsorted(unique_keys, np.minimum(child, up) * n_faces + np.maximum(child, up))]
    # Pointer jumping: the flip of a triangle is the parity of its path to the root.
    flip = parity.copy()
    hop = parent.copy()
    for _ in range(max(1, int(np.ceil(np.log2(max(n_faces, 2)))) + 1)):
        flip ^= np.where(hop == np.arange(n_faces), 0, flip[hop]).astype(np.int8)
        hop = hop[hop]
    flip = flip.astype(bool)
    conflict_edges = (relative.astype(bool) ^ flip[fa] ^ flip[fb])
    conflicts = np.zeros(n_faces, dtype=bool)
    conflicts[fa[conflict_edges]] = True
    conflicts[fb[conflict_edges]] = True
    return labels, n_labels, flip, conflicts, boundary


def _winding_numbers(points: np.ndarray, corners: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
    """(P, n_labels) generalised winding number of each labelled triangle set (corners (F, 3, 3)) at points."""
    out = np.zeros((len(points), n_labels))
    for k, p in enumerate(points):
        r = corners - p
        length = np.linalg.norm(r, axis=2)
        det = np.einsum("ij,ij->i", r[:, 0], np.cross(r[:, 1], r[:, 2]))
        dots = (
            length[:, 0] * length[:, 1] * length[:, 2]
            + np.einsum("ij,ij->i", r[:, 0], r[:, 1]) * length[:, 2]
            + np.einsum("ij,ij->i", r[:, 1], r[:, 2]) * length[:, 0]
            + np.einsum("ij,ij->i", r[:, 2], r[:, 0]) * length[:, 1]
        )
        out[k] = np.bincount(labels, 2 * np.arctan2(det, dots), minlength=n_labels) / (4 * np.pi)
    return out


def _visibility_votes(vertices: np.ndarray, tri: np.ndarray, labels: np.ndarray, n_labels: int) -> np.ndarray:
    """(n_labels,) sum over first hits of rays from outside of +1 (the hit triangle faces the ray) or -1.

    Orthographic ray grids from ``VISIBILITY_VIEWS`` directions spread over the sphere, each covering the
    bounding sphere; float32 ray casting in coordinates relative to the bounding-box centre.
    """
    import open3d as o3d

    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    local = vertices - centre
    radius = float(np.linalg.norm(local, axis=1).max())
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(local.astype(np.float32)), o3d.core.Tensor(tri.astype(np.uint32)))
    n, size = VISIBILITY_VIEWS, VISIBILITY_PIXELS
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    directions = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    helper = np.where(np.abs(directions[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(directions, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(directions, u)
    grid = (np.arange(size) + 0.5) / size * 2 - 1
    gx, gy = (g.ravel() * radius for g in np.meshgrid(grid, grid))
    origins = (-2 * radius * directions[:, None, :] + gx[None, :, None] * u[:, None, :] + gy[None, :, None] * w[:, None, :])
    rays = np.concatenate([origins, np.broadcast_to(directions[:, None, :], origins.shape)], axis=2)
    hits = scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6).astype(np.float32)))
    ids = hits["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(hits["t_hit"].numpy())
    normals = hits["primitive_normals"].numpy().astype(np.float64)
    facing = np.einsum("ij,ij->i", normals, np.repeat(directions, size * size, axis=0)) < 0
    return np.bincount(labels[ids[hit]], np.where(facing[hit], 1.0, -1.0), minlength=n_labels)


def orient_outward(vertices: np.ndarray, triangles: np.ndarray, name: str = "mesh") -> tuple[np.ndarray, OrientationReport]:
    """Triangles (F, 3) re-wound consistently and outward (see the module docstring); vertices unchanged.

    Deterministic; a mesh that is already consistent and outward comes back identical.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    # Decisions depend on signs only: work at O(1) scale around the box centre so nothing over/underflows.
    mid = 0.5 * vertices.min(axis=0) + 0.5 * vertices.max(axis=0)
    vertices = np.ldexp(0.5 * vertices - 0.5 * mid, 1 - int(np.frexp(np.abs(0.5 * vertices - 0.5 * mid).max() or 1.0)[1]))
    tri = np.asarray(triangles).copy()
    labels, n_labels, flip, conflicts, boundary = _patches(tri)
    bad = np.bincount(labels, conflicts, minlength=n_labels) > 0
    flip &= ~bad[labels]  # a non-orientable patch keeps its winding
    tri[flip] = tri[flip][:, ::-1]
    closed = (np.bincount(labels, boundary, minlength=n_labels) == 0) & ~bad
    corners = vertices[tri]
    area_vectors = 0.5 * np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(area_vectors, axis=1)
    # Centroid per patch (area-weighted triangle centroids), then the flux of (x - centroid) through it.
    weight = np.bincount(labels, area, minlength=n_labels)
    safe = np.where(weight > 0, weight, 1.0)
    centre = corners.mean(axis=1)
    centroid = np.stack([np.bincount(labels, area * centre[:, i], minlength=n_labels) for i in range(3)], 1) / safe[:, None]
    flux = np.bincount(labels, np.einsum("ij,ij->i", centre - centroid[labels], area_vectors), minlength=n_labels)
    want = np.ones(n_labels)
    closed_ids = np.flatnonzero(closed)
    if 1 < len(closed_ids) <= MAX_NESTING_PATCHES:
        in_closed = closed[labels]
        first_vertex = vertices[tri[np.unique(labels, return_index=True)[1][closed_ids], 0]]
        winding = _winding_numbers(first_vertex, corners[in_closed], labels[in_closed], n_labels)[:, closed_ids]
        np.fill_diagonal(winding, 0.0)
        depth = (np.abs(winding) > 0.5).sum(axis=1)
        want[closed_ids] = np.where(depth % 2 == 1, -1.0, 1.0)
    extent = np.sqrt(np.maximum(weight, 0.0))
    decided = closed | (np.abs(flux) > OPEN_VOTE_TOLERANCE * weight * extent)
    open_ids = np.flatnonzero(~closed & ~bad)
    if len(open_ids):
        # Open patches: what an outside observer sees is the outside; a double-walled open vessel's inner
        # wall faces the axis, which the centroid flux would get wrong. The flux decides unseen patches.
        votes = _visibility_votes(vertices, tri, labels, n_labels)
        seen = open_ids[votes[open_ids] != 0]
        flux[seen] = votes[seen]
        decided[seen] = True
    decided &= ~bad & (weight > 0)
    outward_flip = decided & (np.sign(flux) == -want)
    tri[outward_flip[labels]] = tri[outward_flip[labels]][:, ::-1]
    n_flipped = int(np.count_nonzero(flip ^ outward_flip[labels]))
    undecided = int(np.count_nonzero(~decided & ~bad))
    if bad.any():
        log.warning("%s: %d patch(es) cannot be oriented consistently (non-orientable); left as they are", name, int(bad.sum()))
    if n_flipped:
        log.info("%s: re-wound %d of %d triangles to face outward", name, n_flipped, len(tri))
    report = OrientationReport(n_labels, int(closed.sum()), n_flipped, int(bad.sum()), undecided)
    return tri, report


__all__ = ["OrientationReport", "orient_outward"]
