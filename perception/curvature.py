"""Vertex normals and curvature estimators (pymeshlab, Open3D), all on the mesh's own vertex order.

Facts this module relies on (pymeshlab 2025.7, checked in ``tests/perception/test_curvature.py`` and
``benchmarks/geometry.py``): "Quadric Fitting" gives |H| within ~0.5 % on a sphere; principal directions
come back unordered and, from "Scale Dependent Quadric Fitting", scaled by the curvature (we normalise and
order them, see ``_order_directions``); the discrete (Meyer et al.) operator gives mean and Gaussian
curvature but no directions; ``autoclean=True`` may delete vertices and re-index, so it is always off and the
vertex count is checked.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from perception.errors import InvalidArgumentError, InvalidMeshError
from perception.isolate import IsolatedCallFailed, run_isolated

log = logging.getLogger(__name__)

#: Curvature estimators offered by :meth:`ObjectModel.compute_curvature`.
CURVATURE_METHODS = ("quadric", "scale_quadric", "discrete")
#: Time limit of an isolated pymeshlab curvature estimate: this many seconds, plus the next per vertex. Far
#: above the normal run time (about 0.05 s per 1,000 vertices), so only a hang reaches it, even on a loaded
#: machine; a falsely timed-out estimate would silently change results.
CHILD_TIMEOUT_S = 30.0
CHILD_TIMEOUT_PER_VERTEX_S = 2e-3


@dataclass(frozen=True)
class Curvature:
    """Per-vertex curvature, in 1/mm, with outward normals: convex bumps have positive ``mean``.

    ``k1 >= k2`` are the principal curvatures, ``dir1``/``dir2`` (V x 3, unit) their directions,
    ``mean = (k1 + k2) / 2`` and ``gaussian = k1 * k2`` (1/mm^2).
    """

    mean: np.ndarray
    gaussian: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    dir1: np.ndarray
    dir2: np.ndarray
    method: str


#: pymeshlab weightings for vertex normals, plus Open3D's mesh and point-cloud estimators.
NORMAL_METHODS = ("angle", "area", "max", "uniform", "open3d", "open3d_pca")
_PYMESHLAB_NORMAL_MODES = {
    "angle": "By Angle",
    "area": "By Area",
    "max": "As defined by N. Max",
    "uniform": "Simple Average",
}
_PRINCIPAL_METHODS = {"quadric": "Quadric Fitting", "scale_quadric": "Scale Dependent Quadric Fitting"}


@contextlib.contextmanager
def quiet_stdout() -> Iterator[None]:
    """Silence C++ chatter on file descriptor 1 (pymeshlab's quadric fits print a line per call)."""
    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def _meshset(vertices: np.ndarray, triangles: np.ndarray):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=triangles))
    return ms


def _corners(vertices: np.ndarray, triangles: np.ndarray):
    """Per triangle corner k: the edge to corner k+1 and to corner k-1, (F, 3, 3) each, and the face cross
    product (F, 3) (twice the area along the unit normal)."""
    p = vertices[triangles]
    to_next = np.roll(p, -1, axis=1) - p
    to_prev = np.roll(p, 1, axis=1) - p
    return to_next, to_prev, np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def _corner_weighted_normals(vertices: np.ndarray, triangles: np.ndarray, method: str) -> np.ndarray:
    """Sum over incident corners of the weighted face normal, (V, 3), not normalised.

    The weightings of pymeshlab's ``compute_normal_per_vertex`` (VCG), re-written in numpy so that no native
    code runs on user data here; ``tests/perception/test_curvature.py`` checks them against pymeshlab:
    ``angle`` unit face normal x corner angle (Thuermer & Wuethrich), ``area`` face cross product (2 x area),
    ``uniform`` unit face normal, ``max`` (e1 x e2) / (|e1|^2 |e2|^2) of the corner's two edges (Max 1999).
    """
    to_next, to_prev, cross = _corners(vertices, triangles)
    if method == "max":
        length2 = np.einsum("fkj,fkj->fk", to_next, to_next) * np.einsum("fkj,fkj->fk", to_prev, to_prev)
        weighted = np.cross(to_next, to_prev) / np.maximum(length2, 1e-300)[:, :, None]
    elif method == "area":
        weighted = np.repeat(cross[:, None, :], 3, axis=1)
    else:
        unit = _unit(cross)
        if method == "uniform":
            weighted = np.repeat(unit[:, None, :], 3, axis=1)
        else:  # angle
            dot = np.einsum("fkj,fkj->fk", to_next, to_prev)
            sine = np.linalg.norm(np.cross(to_next, to_prev), axis=2)
            weighted = np.arctan2(sine, dot)[:, :, None] * unit[:, None, :]
    return _scatter_add(triangles, weighted, len(vertices))


def _scatter_add(triangles: np.ndarray, per_corner: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V, 3) sums of (F, 3 corners, 3) corner vectors onto their vertices (bincount: ~10x ``np.add.at``)."""
    index = triangles.ravel()
    flat = per_corner.reshape(-1, 3)
    return np.stack([np.bincount(index, flat[:, i], minlength=n_vertices) for i in range(3)], axis=1)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray, method: str = "angle") -> np.ndarray:
    """(V, 3) unit vertex normals following the triangle winding.

    Args:
        method: ``angle``/``area``/``max``/``uniform`` (pymeshlab's face-normal weightings, computed here in
            numpy, identical to pymeshlab's to 1e-15), ``open3d`` (Open3D ``compute_vertex_normals``) or
            ``open3d_pca`` (Open3D point-cloud PCA over 30 neighbours, oriented to agree with the
            angle-weighted normal).

    Vertices with no usable normal (isolated or only degenerate faces) get (0, 0, 1).

    Raises:
        InvalidArgumentError: unknown method.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if method in _PYMESHLAB_NORMAL_MODES:
        normals = _corner_weighted_normals(vertices, triangles, method)
    elif method == "open3d":
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles)
        )
        mesh.compute_vertex_normals()
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    elif method == "open3d_pca":
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(vertices))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=30))
        normals = np.asarray(cloud.normals, dtype=np.float64)
        reference = vertex_normals(vertices, triangles, "angle")
        normals *= np.where(np.einsum("ij,ij->i", normals, reference) < 0, -1.0, 1.0)[:, None]
    else:
        raise InvalidArgumentError(f"unknown normal method {method!r}; choose from {', '.join(NORMAL_METHODS)}")
    return _unit_or_default(normals)


def discrete_curvature(
    vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and Gaussian curvature (1/mm, 1/mm^2) per vertex by the discrete operators of Meyer et al. (2003).

    Mean: half the length of the cotangent Laplacian over the mixed Voronoi area, signed positive where it
    points along the outward ``normals`` (convex). Gaussian: angle deficit 2 pi - sum of corner angles over
    the mixed area. pymeshlab's "discrete" estimator (VCG) computes the same (``tests`` check it to 1e-7);
    this copy is numpy only, so it cannot crash the process and serves as the fallback of the pymeshlab
    fits. Vertices with no area (unused, or only degenerate faces) get 0.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    n = len(vertices)
    to_next, to_prev, _ = _corners(vertices, triangles)
    dot = np.einsum("fkj,fkj->fk", to_next, to_prev)
    twice_area = np.linalg.norm(np.cross(to_next, to_prev), axis=2)  # the same for the three corners
    angle = np.arctan2(twice_area, dot)
    cot = np.divide(dot, twice_area, out=np.zeros_like(dot), where=twice_area > 0)
    # Mixed area of corner k: Voronoi (1/8)(|e_k,k+1|^2 cot(k+2) + |e_k,k-1|^2 cot(k+1)) on non-obtuse
    # triangles; on obtuse ones area/2 at the obtuse corner and area/4 at the others.
    next2 = np.einsum("fkj,fkj->fk", to_next, to_next)
    voronoi = (next2 * np.roll(cot, -2, axis=1) + np.roll(next2, 1, axis=1) * np.roll(cot, -1, axis=1)) / 8.0
    obtuse = dot < 0
    area = twice_area / 2.0
    mixed = np.where(obtuse.any(axis=1, keepdims=True), np.where(obtuse, area / 2, area / 4), voronoi)
    mixed_area = np.bincount(triangles.ravel(), mixed.ravel(), minlength=n)
    # Corner k gets (x_k - x_k+1) cot(k+2) + (x_k - x_k-1) cot(k+1): edge (k, k+1) is opposite corner k+2.
    laplacian = _scatter_add(
        triangles, -to_next * np.roll(cot, -2, axis=1)[:, :, None] - to_prev * np.roll(cot, -1, axis=1)[:, :, None], n
    )
    deficit = 2 * np.pi - np.bincount(triangles.ravel(), angle.ravel(), minlength=n)
    ok = mixed_area > 1e-300
    safe_area = np.where(ok, mixed_area, 1.0)
    h_vector = laplacian / (4.0 * safe_area[:, None])
    sign = np.where(np.einsum("ij,ij->i", h_vector, normals) < 0, -1.0, 1.0)
    mean = np.where(ok, sign * np.linalg.norm(h_vector, axis=1), 0.0)
    gaussian = np.where(ok, deficit / safe_area, 0.0)
    return mean, gaussian


def _unit(vectors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length; zero, tiny or non-finite rows become zero."""
    norm = np.linalg.norm(vectors, axis=1, keepdims=True)
    good = np.isfinite(vectors).all(axis=1, keepdims=True) & (norm > 1e-12)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(good, vectors / np.where(good, norm, 1.0), 0.0)


def _unit_or_default(vectors: np.ndarray) -> np.ndarray:
    """Like :func:`_unit`, but degenerate rows become (0, 0, 1)."""
    unit = _unit(vectors)
    unit[~unit.any(axis=1)] = (0.0, 0.0, 1.0)
    return unit


def _tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents orthogonal to each unit normal (used where an estimator gives no direction)."""
    helper = np.where(np.abs(normals[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = _unit_or_default(np.cross(normals, helper))
    return t1, np.cross(normals, t1)


def compute_curvature(model, method: str = "quadric"):
    """Per-vertex :class:`~perception.geometry.Curvature` of ``model`` in 1/mm.

    Mean (H) and Gaussian (K) come from the estimator; k1, k2 = H +- sqrt(max(H^2 - K, 0)), so they are
    consistent with H and K by construction. Non-finite estimates (degenerate neighbourhoods) become 0 and are
    counted in a log warning, so no NaN leaves this function.

    Methods: ``quadric`` (pymeshlab Quadric Fitting), ``scale_quadric`` (Scale Dependent Quadric Fitting,
    fit radius 1 % of the bounding box), ``discrete`` (pymeshlab discrete Meyer et al. operator; its
    directions come from Taubin's approximation).

    Every pymeshlab estimate runs isolated (:func:`perception.isolate.run_isolated`, a forked child with a
    time limit of ``CHILD_TIMEOUT_S`` + ``CHILD_TIMEOUT_PER_VERTEX_S`` per vertex): the fits abort, segfault
    or hang on open meshes and on closed ones alike (a vertex shared by two solids, self-intersections,
    unused vertices, a plain box, a tetrahedron). If the child crashes, runs out of time or pymeshlab refuses
    the mesh, the numpy discrete estimator (:func:`discrete_curvature`, no principal directions) is used
    instead and a warning says so.

    Raises:
        InvalidArgumentError: unknown method.
    """
    if method not in CURVATURE_METHODS:
        raise InvalidArgumentError(
            f"{model.name}: unknown curvature method {method!r}; choose from {', '.join(CURVATURE_METHODS)}"
        )
    mean, gauss, dir1, dir2 = _estimate_safely(model, method)
    bad = ~(np.isfinite(mean) & np.isfinite(gauss))
    if bad.any():
        log.warning("%s: %d vertices had no finite curvature estimate; set to 0", model.name, int(bad.sum()))
        mean[bad], gauss[bad] = 0.0, 0.0
    root = np.sqrt(np.maximum(mean * mean - gauss, 0.0))
    k1, k2 = mean + root, mean - root

    normals = model.vertex_normals
    dir1, dir2 = _order_directions(
        model.vertices, model.triangles, normals, np.nan_to_num(dir1), np.nan_to_num(dir2)
    )
    fallback1, fallback2 = _tangent_basis(normals)
    no_dir = (np.linalg.norm(dir1, axis=1) < 1e-12) | (np.linalg.norm(dir2, axis=1) < 1e-12)
    dir1 = np.where(no_dir[:, None], fallback1, dir1)
    dir2 = np.where(no_dir[:, None], fallback2, dir2)
    return Curvature(mean=mean, gaussian=gauss, k1=k1, k2=k2, dir1=dir1, dir2=dir2, method=method)


def _order_directions(vertices, triangles, normals, dir1, dir2):
    """Make ``dir1`` the k1 (larger curvature) direction and ``dir2`` the k2 one.

    pymeshlab's directions are not reliably ordered (quadric fitting swaps them on a third of a torus,
    Taubin on all of a cylinder) and scale-dependent fitting returns a zero vector where a curvature is 0.
    A zero direction is first rebuilt from the other one and the normal; then, by Euler's formula, the
    one-ring edges closer to the k1 direction bend more (normal curvature of an edge e at a vertex with
    normal n: -2 n.e / |e|^2), so a vertex whose edges bend more across ``dir1`` than along it is swapped.
    """
    ok1 = np.linalg.norm(dir1, axis=1) > 1e-12
    ok2 = np.linalg.norm(dir2, axis=1) > 1e-12
    dir1 = np.where((ok2 & ~ok1)[:, None], np.cross(dir2, normals), dir1)
    dir2 = np.where((ok1 & ~ok2)[:, None], np.cross(normals, dir1), dir2)
    dir1, dir2 = _unit(dir1), _unit(dir2)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    i, j = edges[:, 0], edges[:, 1]
    edge = vertices[j] - vertices[i]
    height = np.einsum("ij,ij->i", normals[i], edge)
    bend = -2.0 * height / np.maximum(np.einsum("ij,ij->i", edge, edge), 1e-300)
    tangent = edge - height[:, None] * normals[i]
    cos2 = np.einsum("ij,ij->i", tangent, dir1[i]) ** 2 / np.maximum(np.einsum("ij,ij->i", tangent, tangent), 1e-300)
    swap = (np.bincount(i, bend * (cos2 - 0.5), minlength=len(vertices)) < 0)[:, None]
    return np.where(swap, dir2, dir1), np.where(swap, dir1, dir2)


def _estimate_safely(model, method: str):
    """The pymeshlab estimate, run in a forked child; the numpy discrete estimate where that fails (logged)."""
    import pymeshlab

    timeout = CHILD_TIMEOUT_S + CHILD_TIMEOUT_PER_VERTEX_S * model.n_vertices
    what = f"{model.name}: pymeshlab {method} curvature"
    try:
        return run_isolated(_estimate, model.vertices, model.triangles, method, model.name, timeout_s=timeout, what=what)
    except IsolatedCallFailed as exc:
        reason = exc.reason
    except (pymeshlab.PyMeshLabException, InvalidMeshError) as exc:
        reason = f"refused the mesh ({exc})"
    log.warning("%s: pymeshlab %s curvature %s; using the numpy discrete estimator", model.name, method, reason)
    mean, gauss = discrete_curvature(model.vertices, model.triangles, model.vertex_normals)
    n = model.n_vertices
    return mean, gauss, np.full((n, 3), np.nan), np.full((n, 3), np.nan)


def _estimate(vertices: np.ndarray, triangles: np.ndarray, method: str, name: str):
    """Raw pymeshlab estimates: mean, Gaussian, dir1, dir2 (may hold NaN)."""
    import pymeshlab

    ms = _meshset(vertices, triangles)
    n = len(vertices)

    def scalar(filter_name: str, **kwargs) -> np.ndarray:
        with quiet_stdout():
            getattr(ms, filter_name)(**kwargs)
        mesh = ms.current_mesh()
        if mesh.vertex_number() != n:  # pymeshlab must not re-index behind our back
            raise InvalidMeshError(f"{name}: pymeshlab changed the vertex count during {filter_name}")
        return np.asarray(mesh.vertex_scalar_array(), dtype=np.float64).copy()

    if method == "discrete":
        mean = scalar("compute_scalar_by_discrete_curvature_per_vertex", curvaturetype="Mean Curvature")
        gauss = scalar("compute_scalar_by_discrete_curvature_per_vertex", curvaturetype="Gaussian Curvature")
        try:
            kwargs = {"method": "Taubin approximation", "curvcolormethod": "None", "autoclean": False}
            scalar("compute_curvature_principal_directions_per_vertex", **kwargs)
        except pymeshlab.PyMeshLabException:  # non-manifold: no directions; tangent-basis fallback applies
            return mean, gauss, np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    else:
        kwargs = {"method": _PRINCIPAL_METHODS[method], "autoclean": False}
        if method == "scale_quadric":
            kwargs["scale"] = pymeshlab.PercentageValue(1.0)
        mean = scalar("compute_curvature_principal_directions_per_vertex", curvcolormethod="Mean Curvature", **kwargs)
        gauss = scalar(
            "compute_curvature_principal_directions_per_vertex", curvcolormethod="Gaussian Curvature", **kwargs
        )
    mesh = ms.current_mesh()
    dir1 = np.asarray(mesh.vertex_curvature_principal_dir1_matrix(), dtype=np.float64)
    dir2 = np.asarray(mesh.vertex_curvature_principal_dir2_matrix(), dtype=np.float64)
    return mean, gauss, dir1, dir2
