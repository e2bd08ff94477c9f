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

from perception.errors import InvalidMeshError

log = logging.getLogger(__name__)

#: Curvature estimators offered by :meth:`ObjectModel.compute_curvature`.
CURVATURE_METHODS = ("quadric", "scale_quadric", "discrete")


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


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray, method: str = "angle") -> np.ndarray:
    """(V, 3) unit vertex normals following the triangle winding.

    Args:
        method: ``angle``/``area``/``max``/``uniform`` (pymeshlab face-normal weightings), ``open3d``
            (Open3D ``compute_vertex_normals``) or ``open3d_pca`` (Open3D point-cloud PCA over 30
            neighbours, oriented to agree with the angle-weighted normal).

    Vertices with no usable normal (isolated or only degenerate faces) get (0, 0, 1).
    """
    if method in _PYMESHLAB_NORMAL_MODES:
        ms = _meshset(vertices, triangles)
        ms.compute_normal_per_vertex(weightmode=_PYMESHLAB_NORMAL_MODES[method])
        normals = np.asarray(ms.current_mesh().vertex_normal_matrix(), dtype=np.float64)
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
        raise ValueError(f"unknown normal method {method!r}; choose from {NORMAL_METHODS}")
    return _unit_or_default(normals)


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

    pymeshlab's quadric fits abort the process (a double free) on some open meshes, e.g. a one-triangle-wide
    band whose vertices all lie on the boundary (``psb_open/Bottle_m489``). On meshes that are not watertight
    the fit therefore runs in a forked child; if the child dies, the discrete estimator is used instead and a
    warning says so.
    """
    if method not in CURVATURE_METHODS:
        raise ValueError(f"unknown curvature method {method!r}; choose from {', '.join(CURVATURE_METHODS)}")
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
    """Run the estimator, isolating pymeshlab crashes, and fall back where pymeshlab refuses the mesh.

    Fallbacks, each logged: on a refusal or crash, the discrete estimator on a manifold copy (non-manifold
    edges and vertices split, values mapped back by position); if even that fails, zeros.
    """
    import concurrent.futures
    import multiprocessing

    import pymeshlab

    args = (model.vertices, model.triangles, method, model.name)
    if model.is_watertight:
        return _estimate(*args)
    try:
        # pymeshlab aborts the whole process on some open meshes: run it in a forked child.
        with concurrent.futures.ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("fork"), initializer=_quiet_child
        ) as pool:
            return pool.submit(_estimate, *args).result()
    except (concurrent.futures.process.BrokenProcessPool, pymeshlab.PyMeshLabException) as exc:
        reason = "crashed" if isinstance(exc, concurrent.futures.process.BrokenProcessPool) else "refused"
    log.warning("%s: pymeshlab %s curvature %s on this open mesh; using 'discrete'", model.name, method, reason)
    try:
        vertices, triangles, index = _manifold_copy(model.vertices, model.triangles)
        mean, gauss, dir1, dir2 = _estimate(vertices, triangles, "discrete", model.name)
        return mean[index], gauss[index], dir1[index], dir2[index]
    except (pymeshlab.PyMeshLabException, InvalidMeshError):
        log.warning("%s: no curvature estimator accepts this mesh; curvature set to 0", model.name)
        n = model.n_vertices
        return np.zeros(n), np.zeros(n), np.full((n, 3), np.nan), np.full((n, 3), np.nan)


def _quiet_child() -> None:
    """In the forked curvature child: an expected abort should not print a stack or glibc's message."""
    import faulthandler

    faulthandler.disable()
    os.environ["LIBC_FATAL_STDERR_"] = "1"  # glibc's fatal messages go to stderr, not the terminal
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)


def _manifold_copy(vertices: np.ndarray, triangles: np.ndarray):
    """Split non-manifold edges and vertices; return the copy and, per original vertex, a copy index."""
    from scipy.spatial import cKDTree

    ms = _meshset(vertices, triangles)
    ms.meshing_repair_non_manifold_edges(method="Remove Faces")
    ms.meshing_repair_non_manifold_vertices()
    ms.meshing_remove_unreferenced_vertices()
    mesh = ms.current_mesh()
    copy_vertices = np.asarray(mesh.vertex_matrix(), dtype=np.float64)
    _, index = cKDTree(copy_vertices).query(vertices)
    return copy_vertices, np.asarray(mesh.face_matrix(), dtype=np.int64), index


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
