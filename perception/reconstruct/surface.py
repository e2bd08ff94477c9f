"""Oriented points -> a triangle surface -> :class:`~perception.geometry.ObjectModel`; a surface's error against
the true one.

:func:`load_points`: a point-cloud file (:mod:`~perception.reconstruct.pointfiles`), an
``open3d.geometry.PointCloud`` or an array -> outliers removed -> normals estimated and oriented -> surface
(screened Poisson trimmed by density; ball pivoting or alpha shapes as alternatives) -> ``ObjectModel``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import open3d as o3d

from perception import meshio
from perception.errors import InvalidArgumentError, InvalidMeshError
from perception.geometry import DEFAULT_SIZE_MM, ObjectModel, normalize
from perception.isolate import IsolatedCallFailed, run_isolated
from perception.reconstruct.pointfiles import read_points
from perception.reconstruct.points import _as_points, _clean, estimate_normals, mean_spacing, validate_points

#: Surface methods of :func:`surface_from_points`.
METHODS = ("poisson", "ball_pivoting", "alpha")
#: Surface pieces with fewer triangles than this fraction of the largest piece are dropped as specks.
MIN_PIECE = 0.05
#: Default alpha of alpha shapes, as a fraction of the cloud's bounding-box diagonal.
ALPHA_FRACTION = 0.2


#: Time limit of an isolated surface reconstruction (:func:`surface_from_points`): this many seconds, plus the
#: next per point, plus (Poisson) the last times 4 per octree level above depth 8 (each level quadruples the
#: surface). Far above the normal run time (about 1 s for 6,000 points at depth 8 on one core), so only a hang
#: reaches it, even on a loaded machine.
CHILD_TIMEOUT_S = 120.0
CHILD_TIMEOUT_PER_POINT_S = 1e-3
CHILD_TIMEOUT_POISSON_S = 30.0


def _centre(points: np.ndarray, name: str) -> np.ndarray:
    """The midpoint of the bounding box of ``points`` (mm), about which they are reconstructed: Open3D's surface
    methods work in float (Poisson) or with absolute tolerances (Qhull) and fail on a cloud whose extent is tiny
    next to its distance from the origin (Poisson segfaults at 1e-8, Qhull reports cospherical input). The
    midpoint of a translated cloud is the translated midpoint (exactly, where the translated coordinates are
    exact), so the surface does not depend on where the cloud sits.

    Raises:
        InvalidMeshError: all points coincide, or the cloud spans more than the float range.
    """
    low, high = points.min(axis=0), points.max(axis=0)
    centre = low + 0.5 * (high - low) if np.isfinite(high - low).all() else 0.5 * low + 0.5 * high
    largest = float(np.abs(points - centre).max())
    if not (np.isfinite(largest) and largest > 0) or largest > 2.0**1000:
        raise InvalidMeshError(f"{name}: the points span no extent (all coincide) or exceed the float range")
    return centre


def _check_alpha(alpha_mm, name: str) -> None:
    """Raises InvalidArgumentError unless ``alpha_mm`` is None or a finite positive number."""
    if alpha_mm is not None and not (
        isinstance(alpha_mm, (int, float, np.number)) and not isinstance(alpha_mm, bool)
        and np.isfinite(alpha_mm) and alpha_mm > 0
    ):
        raise InvalidArgumentError(f"{name}: alpha_mm must be a finite positive length in mm or None, got {alpha_mm!r}")


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

    The surface is built on the points centred on their bounding box's midpoint and scaled into the unit cube by
    a power of two (the clean-up after it in millimetres), and its vertices mapped back: the result does not
    depend on where the cloud sits (a cloud translated by 1e6 mm, its coordinates exact, gives the same triangles
    and the vertices translated, to the rounding of the translated coordinates), and a cloud far from the origin
    (1e8 times its size away, where Open3D's Poisson segfaults on raw coordinates) is an ordinary one. The Open3D
    calls run in a forked child with a time limit (:func:`perception.isolate.run_isolated`; about 30 ms more per
    call): a native crash or hang there is this function's error, never the caller's death.

    Raises:
        InvalidArgumentError: unknown method or bad parameter.
        InvalidMeshError: points or normals not finite or badly shaped, or no surface could be built (Open3D
            refused the points, crashed, or ran out of time).
    """
    if method not in METHODS:
        raise InvalidArgumentError(f"{name}: unknown surface method {method!r}; choose one of {', '.join(METHODS)}")
    if not (isinstance(poisson_depth, (int, np.integer)) and 4 <= poisson_depth <= 12):
        raise InvalidArgumentError(f"{name}: poisson_depth must be an integer in 4..12, got {poisson_depth!r}")
    if density_trim is not None and not (np.isfinite(density_trim) and density_trim > 0):
        raise InvalidArgumentError(f"{name}: density_trim must be a positive number of octree levels or None")
    _check_alpha(alpha_mm, name)
    points = _as_points(points, name)
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != points.shape or not np.isfinite(normals).all():
        raise InvalidMeshError(f"{name}: normals must be finite and shaped like the points {points.shape}, "
                               f"got shape {normals.shape}")
    if len(points) < 4:
        raise InvalidMeshError(f"{name}: only {len(points)} points; a surface needs at least 4")
    centre = _centre(points, name)
    vertices, triangles = _surface_isolated(
        points - centre, normals, method, int(poisson_depth), density_trim, max_triangles,
        None if alpha_mm is None else float(alpha_mm), name,
    )
    return vertices + centre, triangles


def _surface_isolated(points, normals, method, poisson_depth, density_trim, max_triangles, alpha_mm, name):
    """:func:`_surface` run in a forked child; Open3D's failures as InvalidMeshError."""
    timeout = CHILD_TIMEOUT_S + CHILD_TIMEOUT_PER_POINT_S * len(points)
    if method == "poisson":
        timeout += CHILD_TIMEOUT_POISSON_S * 4.0 ** max(poisson_depth - 8, 0)
    what = f"{name}: Open3D {method} surface from {len(points)} points"
    try:
        return run_isolated(_surface, points, normals, method, poisson_depth, density_trim, max_triangles, alpha_mm,
                            name, timeout_s=timeout, what=what)
    except IsolatedCallFailed as exc:
        hint = ("each child forked waited on a lock another thread of this process held at the fork"
                if exc.kind == "deadlocked" else "check the cloud: duplicated, degenerate or extreme points")
        raise InvalidMeshError(f"{what}: Open3D {exc.reason}; no surface was built ({hint})") from None
    except RuntimeError as exc:  # Open3D's and Qhull's own errors: precision, degenerate input
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        first = re.sub(r"\x1b\[[0-9;]*m", "", first)  # Open3D colours its messages for a terminal
        raise InvalidMeshError(f"{what}: Open3D refused the points ({first[:300]}); no surface was built") from None


def _surface(
    points: np.ndarray,
    normals: np.ndarray,
    method: str,
    poisson_depth: int,
    density_trim: float | None,
    max_triangles: int | None,
    alpha_mm: float | None,
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """The surface of :func:`surface_from_points` through ``points`` centred about the origin (mm): the raw Open3D
    calls, which may crash (run it isolated).

    The reconstruction itself sees the points scaled into the unit cube by a power of two (exact both ways); the
    clean-up after it runs in the given millimetres again: Open3D's quadric decimation tests its quadrics against
    absolute thresholds, so it simplifies a mesh in millimetres and the same mesh in other units differently."""
    scale = float(np.ldexp(1.0, int(np.frexp(np.abs(points).max())[1])))  # max |unit| in [0.5, 1)
    unit = points / scale
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(unit))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    if method == "poisson":
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=int(poisson_depth), n_threads=1
        )
        density = np.asarray(density)
        if density_trim is not None and len(density):
            mesh.remove_vertices_by_mask(density < np.quantile(density, 0.9) - density_trim)
        mesh.remove_triangles_by_mask(_paired_faces(np.asarray(mesh.triangles)))
    elif method == "ball_pivoting":
        spacing = mean_spacing(unit)
        radii = o3d.utility.DoubleVector([spacing, 2 * spacing, 4 * spacing])
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    else:
        diagonal = float(np.linalg.norm(unit.max(axis=0) - unit.min(axis=0)))
        alpha = ALPHA_FRACTION * diagonal if alpha_mm is None else float(alpha_mm) / scale
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(cloud, alpha)
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * scale)  # back to millimetres
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
    cut = method == "poisson" and not mesh.is_edge_manifold()
    if cut:
        # Marching cubes and decimation leave an edge with four faces here and there: drop those faces and
        # close the few-edge holes they leave.
        mesh.remove_non_manifold_edges()
        mesh.remove_unreferenced_vertices()
    vertices, triangles = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
    if cut:
        vertices, triangles = close_holes(vertices, triangles)
    if method == "poisson":  # the clean-up above can leave a pair too: two faces on one edge loop, a flat pillow
        paired = _paired_faces(triangles)
        if paired.any():
            triangles = triangles[~paired]
            used = np.unique(triangles)
            vertices, triangles = vertices[used], np.searchsorted(used, triangles)
    return vertices, triangles


def _paired_faces(triangles: np.ndarray) -> np.ndarray:
    """(F,) True for every face on the same three vertices as another one. Open3D's Poisson can emit a face twice
    (both windings) where two sheets meet in a thin wall: four faces on each of its edges. The pair encloses
    nothing; dropping both keeps the rest closed (a mesh clean-up that kept one would leave a hole)."""
    if not len(triangles):
        return np.zeros(0, dtype=bool)
    _, inverse, counts = np.unique(np.sort(triangles, axis=1), axis=0, return_inverse=True, return_counts=True)
    return counts[inverse.ravel()] > 1


def close_holes(
    vertices: np.ndarray, triangles: np.ndarray, max_edges: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) with each hole of at most ``max_edges`` boundary edges closed by a fan around its
    centroid (a new vertex), wound like the faces beside it. A hole is one loop of boundary edges: two holes that
    touch at a vertex (where a non-manifold edge was cut out) get a fan each, since one fan over both would put
    four faces on the edge from that vertex to its centre."""
    triangles = np.asarray(triangles, dtype=np.int64)
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    keys = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
    if not len(border):
        return vertices, triangles
    loops = _boundary_loops(border)
    small = [loop for loop in loops if len(loop) <= max_edges]
    if not small:
        return vertices, triangles
    n = len(vertices)
    centres = np.array([vertices[border[loop, 0]].mean(axis=0) for loop in small])
    fan = np.concatenate([np.stack([border[loop, 1], border[loop, 0], np.full(len(loop), n + i)], axis=1)
                          for i, loop in enumerate(small)])
    return np.concatenate([vertices, centres]), np.concatenate([triangles, fan])


def _boundary_loops(border: np.ndarray) -> list[np.ndarray]:
    """The boundary edges ``border`` (E, 2) split into simple loops (each an array of edge rows, in order), walked
    without regard to their direction (the winding may still be mixed here): a walk that comes back to a vertex it
    passed cuts off the loop since then, so holes that touch at a vertex come out apart. Edges on no loop (an
    open chain) are left out."""
    incident: dict[int, list[int]] = {}
    for e, (a, b) in enumerate(border.tolist()):
        incident.setdefault(a, []).append(e)
        incident.setdefault(b, []).append(e)
    # Edges on no loop go first: a face's edge from a vertex to itself, then open chains, pruned from their loose
    # ends inwards (a walk that took one would dead-end and drop the loop it started on).
    used = border[:, 0] == border[:, 1]
    degree = {v: sum(not used[e] for e in es) for v, es in incident.items()}
    loose = [v for v, d in degree.items() if d == 1]
    while loose:
        v = loose.pop()
        e = next((e for e in incident[v] if not used[e]), None)
        if e is None:
            continue
        used[e] = True
        for w in border[e].tolist():
            degree[w] -= 1
            if degree[w] == 1:
                loose.append(w)
    loops = []
    for first in range(len(border)):
        if used[first]:
            continue
        used[first] = True
        path, edges = [int(border[first, 0])], [first]  # edges[i] joins path[i] and path[i + 1]
        position = {path[0]: 0}
        at = int(border[first, 1])
        while True:
            if at in position:  # a loop closed: cut it off and walk on from here
                cut = position[at]
                loops.append(np.asarray(edges[cut:], dtype=np.int64))
                for v in path[cut + 1:]:
                    del position[v]
                del path[cut + 1:], edges[cut:]
            else:
                position[at] = len(path)
                path.append(at)
            nxt = next((e for e in incident[at] if not used[e]), None)
            if nxt is None:
                break
            used[nxt] = True
            edges.append(nxt)
            a, b = border[nxt]
            at = int(b if a == at else a)
    return loops


def _to_model(vertices, triangles, *, name, label, size_mm, source, pre_transform=None) -> ObjectModel:
    from perception.orientation import orient_outward

    where = source or name
    vertices, triangles = meshio.validate_arrays(vertices, triangles, where)
    vertices, triangles, _ = meshio.repair(vertices, triangles, None, where)
    # Poisson from outward normals is outward already; ball pivoting and alpha shapes may wind either way.
    triangles, _ = orient_outward(vertices, triangles, where)
    transform = np.eye(4) if pre_transform is None else pre_transform
    if size_mm is not None:
        vertices, scale = normalize(vertices, size_mm, triangles=triangles)
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
    estimated (:func:`~perception.reconstruct.points.estimate_normals`). ``size_mm=None`` keeps the cloud's own scale and position.
    All steps run on the cloud centred on its bounding box's midpoint (the surface mapped back; see
    :func:`surface_from_points`): the result does not depend on where the cloud sits, however far from the origin.

    Raises:
        InvalidMeshError: a bad cloud (:func:`~perception.reconstruct.points.validate_points`), bad normals, or no surface.
        InvalidArgumentError: unknown surface method or bad parameter.
    """
    where = source or name  # messages name the file when there is one
    _check_alpha(alpha_mm, where)
    points = validate_points(points, where)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        norm = np.linalg.norm(normals, axis=1, keepdims=True) if normals.shape == points.shape else None
        if norm is None or not np.isfinite(normals).all() or (norm == 0).any():
            raise InvalidMeshError(f"{where}: normals must be finite, non-zero and shaped like the points {points.shape}")
        normals = normals / norm
    # Everything from here runs on the cloud centred (see surface_from_points): Open3D's neighbourhood
    # statistics and normal estimation (covariances from raw moments) lose their precision on a cloud far
    # from the origin, and the result must not depend on where the cloud sits.
    centre = _centre(points, where)
    points = points - centre
    if viewpoints is not None:
        viewpoints = np.asarray(viewpoints, dtype=np.float64)
        if viewpoints.shape not in ((3,), points.shape) or not np.isfinite(viewpoints).all():
            raise InvalidArgumentError(f"{where}: viewpoints must be a finite (3,) point or (N, 3) array shaped like "
                                       f"the points {points.shape}, got shape {viewpoints.shape}")
        viewpoints = viewpoints - centre
    # Repeated points (a cloud merged twice, a scanner's duplicates) would fill the k nearest neighbours of the normal
    # estimate and the outlier statistics with copies: keep the first of each, in order.
    _, first = np.unique(points, axis=0, return_index=True)
    if len(first) < len(points):
        keep = np.sort(first)
        points = points[keep]
        normals = None if normals is None else normals[keep]
        viewpoints = viewpoints[keep] if viewpoints is not None and np.ndim(viewpoints) == 2 else viewpoints
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
    vertices = vertices + centre
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


def sample_surface(model: ObjectModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points drawn uniformly on ``model``'s surface (triangles chosen by area, then uniform in the triangle),
    mm, from ``rng``.

    Raises:
        InvalidMeshError: the mesh has zero surface area.
    """
    areas = model.triangle_areas
    if areas.sum() <= 0:
        raise InvalidMeshError(f"{model.name}: zero surface area")
    tri = rng.choice(model.n_triangles, n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = (model.vertices[model.triangles[tri, i]] for i in range(3))
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


#: With captured points given, :func:`surface_error` also measures the samples within this of one (mm): the surface
#: a camera saw, apart from what closing the rest added.
SEEN_MM = 2.0


def surface_error(model: ObjectModel, truth: ObjectModel, *, n_samples: int = 20000, seed: int = 0,
                  seen=None) -> dict:
    """How far a reconstruction lies from the true surface, mm.

    Accuracy: ``n_samples`` points drawn uniformly (area-weighted, seeded) on ``model``, each one's
    distance to ``truth``: ``mean_mm``, ``p95_mm``, ``max_mm``. Completeness: the same from points on
    ``truth`` to ``model`` (``coverage_mean_mm``, ``coverage_p95_mm``); parts no camera saw (the bottom
    on the table) count here. ``seen``: the (N, 3) captured points; adds the accuracy of the samples within
    :data:`SEEN_MM` of one (``seen_mean_mm``, ``seen_p95_mm``, and ``seen_fraction`` of the samples), leaving out
    what a closed reconstruction adds where no camera looked (a mug's filled hollow).

    Raises:
        InvalidMeshError: a mesh with zero area, or ``seen`` not finite (N, 3) points near none of the samples.
    """
    rng = np.random.default_rng(seed)
    samples = sample_surface(model, n_samples, rng)
    _, dist = truth.closest_points(samples)
    _, back = model.closest_points(sample_surface(truth, n_samples, rng))
    out = {
        "mean_mm": float(dist.mean()),
        "p95_mm": float(np.quantile(dist, 0.95)),
        "max_mm": float(dist.max()),
        "coverage_mean_mm": float(back.mean()),
        "coverage_p95_mm": float(np.quantile(back, 0.95)),
    }
    if seen is not None:
        from scipy.spatial import cKDTree

        seen = np.asarray(seen, dtype=np.float64)
        if seen.ndim != 2 or seen.shape[1] != 3 or not len(seen) or not np.isfinite(seen).all():
            raise InvalidMeshError(f"{model.name}: seen must be finite (N, 3) captured points, got {seen.shape}")
        near = cKDTree(seen).query(samples, distance_upper_bound=SEEN_MM)[0] <= SEEN_MM
        if not near.any():
            raise InvalidMeshError(f"{model.name}: no part of the surface lies within {SEEN_MM:g} mm of a seen point")
        out |= {"seen_mean_mm": float(dist[near].mean()), "seen_p95_mm": float(np.quantile(dist[near], 0.95)),
                "seen_fraction": float(near.mean())}
    return out


__all__ = ["METHODS", "SEEN_MM", "close_holes", "load_points", "points_to_model", "sample_surface", "surface_error", "surface_from_points"]
