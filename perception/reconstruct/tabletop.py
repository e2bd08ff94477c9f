"""Tabletop scenes: RGB-D points -> the table plane -> the objects standing on it -> the one to touch (mm)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from perception.errors import InvalidArgumentError, InvalidMeshError
from perception.reconstruct.points import MIN_POINTS, _as_points, estimate_normals

log = logging.getLogger(__name__)


@dataclass
class Cluster:
    """One object segmented from a tabletop scene.

    Attributes:
        points: (N, 3) world points, mm.
        colors: (N, 3) RGB in [0, 1].
        viewpoints: (N, 3) camera centre each point was seen from, mm.
        centroid: (3,) mean of the (visible) points, mm.
        center: (3,) centre of the prism the cluster stands in: the centroid's foot on the table raised
            by half the height, mm (a camera sees the top and front only; this estimates the object's centre).
        height_mm: largest height above the table plane, mm.
    """

    points: np.ndarray
    colors: np.ndarray
    viewpoints: np.ndarray
    centroid: np.ndarray
    center: np.ndarray
    height_mm: float


@dataclass
class TableScene:
    """A segmented tabletop: the table plane and the object clusters on it, largest first.

    Attributes:
        plane: (4,) a, b, c, d with unit normal (a, b, c) pointing up (towards the cameras): a x + b y + c z + d = 0.
        n_table_points: inliers of the plane.
        clusters: the objects, largest first.
        points, colors, labels: the points after down-sampling (mm), their RGB in [0, 1] and their labels
            (-2 table, -1 noise or off the table, k cluster k).
        floor_mm: the table's own noise: points lower than this above the plane cannot be told from it
            (three robust standard deviations of the inliers' heights, at most the plane tolerance), mm.
    """

    plane: np.ndarray
    n_table_points: int
    clusters: list[Cluster] = field(default_factory=list)
    points: np.ndarray | None = None
    colors: np.ndarray | None = None
    labels: np.ndarray | None = None
    floor_mm: float = 0.0


def frames_to_points(frames, *, max_depth_mm: float = 1500.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (mm), colours and viewpoints of all valid pixels of ``frames`` (depth <= ``max_depth_mm``).

    Raises:
        InvalidMeshError: no frame has any depth.
    """
    pts, cols, views = [], [], []
    for frame in frames:
        p, c = frame.points(frame.valid & (frame.depth_mm <= max_depth_mm))
        pts.append(p)
        cols.append(c)
        views.append(np.broadcast_to(frame.camera_position, p.shape))
    if not pts or sum(len(p) for p in pts) == 0:
        raise InvalidMeshError(f"{frames[0].name if frames else 'frames'}: no valid depth in the capture")
    return np.concatenate(pts), np.concatenate(cols), np.concatenate(views)


def segment_table(
    points: np.ndarray,
    colors: np.ndarray | None = None,
    viewpoints: np.ndarray | None = None,
    *,
    voxel_mm: float = 3.0,
    plane_tolerance_mm: float = 6.0,
    cluster_eps_mm: float = 8.0,
    min_cluster_points: int = 100,
    max_height_mm: float = 400.0,
    up_hint: np.ndarray | None = None,
    method: str = "euclidean",
    smooth_deg: float = 30.0,
    color_tolerance: float = 0.1,
    seed: int = 0,
) -> TableScene:
    """Find the table plane (RANSAC) and cluster what stands on it (DBSCAN), all in mm.

    The cloud is down-sampled on a ``voxel_mm`` grid; the plane with the most inliers within
    ``plane_tolerance_mm`` is the table, refined by least squares on its inliers; its normal points
    towards ``up_hint`` (default: the mean viewpoint, or -y in camera coordinates, i.e. image up). Points
    more than ``plane_tolerance_mm`` and at most ``max_height_mm`` above it are clustered with DBSCAN
    (``cluster_eps_mm``); clusters under ``min_cluster_points`` are dropped. Each cluster then grows down
    into the points between the table's noise floor (:attr:`TableScene.floor_mm`) and
    ``plane_tolerance_mm`` that join it within ``cluster_eps_mm`` and lie under its footprint: the lowest
    millimetres of an object (a glass's foot, the base of a wall) are not table.

    ``method="euclidean"`` clusters by distance alone (DBSCAN), right for one object or objects apart.
    ``method="smooth"`` separates objects that touch: neighbours (within ``cluster_eps_mm``) are joined
    only where their normals differ by less than ``smooth_deg`` and their colours by less than
    ``color_tolerance`` (max over RGB in [0, 1]); a region-growing segmentation (as PCL's
    ``RegionGrowingRGB``) that may split one object with sharp creases or strong print into several.

    Raises:
        InvalidMeshError: too few points, or no plane found.
        InvalidArgumentError: an unknown method.
    """
    if method not in ("euclidean", "smooth"):
        raise InvalidArgumentError(f"scene: unknown segmentation method {method!r} (euclidean or smooth)")
    points = _as_points(points, "scene")
    if len(points) < 3 * MIN_POINTS:
        raise InvalidMeshError(f"scene: only {len(points)} points with depth; cannot find a table")
    colors = np.zeros_like(points) if colors is None else np.asarray(colors, dtype=np.float64)
    viewpoints = np.zeros_like(points) if viewpoints is None else np.asarray(viewpoints, dtype=np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    # Carry colour and viewpoint through the voxel average: colours as colours, viewpoints as normals.
    cloud.colors = o3d.utility.Vector3dVector(colors)
    cloud.normals = o3d.utility.Vector3dVector(viewpoints)
    if voxel_mm > 0:
        cloud = cloud.voxel_down_sample(voxel_mm)
    pts = np.asarray(cloud.points).copy()
    cols = np.asarray(cloud.colors).copy()
    views = np.asarray(cloud.normals).copy()
    o3d.utility.random.seed(int(seed))
    cloud.normals = o3d.utility.Vector3dVector()
    _, inliers = cloud.segment_plane(plane_tolerance_mm, 3, 1000)
    inliers = np.asarray(inliers, dtype=np.int64)
    if len(inliers) < 3:
        raise InvalidMeshError("scene: no table plane found")
    # Least-squares refinement on the inliers, twice, re-selecting them: Open3D's RANSAC runs on several
    # threads and may return another of equally good candidates under load; the refit plane does not.
    for _ in range(2):
        centre = pts[inliers].mean(axis=0)
        normal = np.linalg.svd(pts[inliers] - centre, full_matrices=False)[2][2]
        inliers = np.nonzero(np.abs((pts - centre) @ normal) <= plane_tolerance_mm)[0]
    up = np.asarray(up_hint, dtype=np.float64) if up_hint is not None else views.mean(axis=0) - centre
    if np.linalg.norm(up) < 1e-9:
        up = np.array([0.0, -1.0, 0.0])
    if normal @ up < 0:
        normal = -normal
    plane = np.r_[normal, -normal @ centre]
    height = pts @ normal + plane[3]
    # The table's noise, robustly (MAD): above 3 sigma a point stands out of the plane.
    floor = min(plane_tolerance_mm, 3 * 1.4826 * float(np.median(np.abs(height[inliers]))))
    labels = np.full(len(pts), -1, dtype=np.int64)
    on_table = np.abs(height) <= plane_tolerance_mm
    labels[on_table] = -2
    above = (height > plane_tolerance_mm) & (height <= max_height_mm)
    above = np.nonzero(above)[0]
    if on_table.sum() >= 3 and len(above):
        # Objects *on* the table: above it and inside the convex hull of its inliers, seen from above
        # (the polygonal prism of PCL's tabletop segmentation); drops walls, robots and people beside it.
        above = above[_inside_table(pts[above], pts[on_table], normal)]
    clusters: list[Cluster] = []
    if len(above):
        if method == "smooth":
            raw = _smooth_components(
                pts[above], cols[above], views[above], cluster_eps_mm, smooth_deg, color_tolerance
            )
        else:
            sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[above]))
            raw = np.asarray(sub.cluster_dbscan(cluster_eps_mm, 10), dtype=np.int64)
        found = []
        for k in range(raw.max(initial=-1) + 1):
            idx = above[raw == k]
            if len(idx) >= min_cluster_points:
                found.append(idx)
        # Order by size, then by first index: independent of DBSCAN's label numbering.
        found.sort(key=lambda idx: (-len(idx), int(idx[0])))
        low = np.nonzero(on_table & (height > floor))[0]
        if len(low):
            low = low[_inside_table(pts[low], pts[on_table], normal)]
        taken = np.zeros(len(low), dtype=bool)
        for k, idx in enumerate(found):
            grown = _grow_down(pts, idx, low, taken, cluster_eps_mm, normal)
            idx = found[k] = np.sort(np.concatenate([idx, grown]))
            labels[idx] = k
            top = float(height[idx].max())
            mean = pts[idx].mean(axis=0)
            # Prism centre: the mean's foot on the table, raised by half the height.
            center = mean - (height[idx].mean() - 0.5 * top) * normal
            clusters.append(Cluster(pts[idx], cols[idx], views[idx], mean, center, top))
    log.info("scene: table %d points (floor %.1f mm), %d clusters", int(on_table.sum()), floor, len(clusters))
    return TableScene(plane, int(on_table.sum()), clusters, pts, cols, labels, floor)


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes (u, v) spanning the plane with unit ``normal``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _grow_down(
    pts: np.ndarray, idx: np.ndarray, low: np.ndarray, taken: np.ndarray, eps: float, normal: np.ndarray
) -> np.ndarray:
    """The points ``low`` (indices into ``pts``, not yet ``taken``) reachable from cluster ``idx`` in steps
    of at most ``eps`` mm, each within ``eps`` of the cluster's footprint (the convex hull of its points
    seen from above the table: growth cannot creep along the table). Marks them in ``taken``."""
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    if not len(low):
        return low
    u, v = _plane_axes(normal)
    flat = lambda p: np.stack([p @ u, p @ v], axis=1)
    try:
        hull = ConvexHull(flat(pts[idx])).equations
    except (QhullError, ValueError):
        return low[:0]
    allowed = np.all(flat(pts[low]) @ hull[:, :2].T + hull[:, 2] <= eps, axis=1) & ~taken
    tree = cKDTree(pts[low])
    frontier = pts[idx]
    grown = np.zeros(len(low), dtype=bool)
    while len(frontier):
        hits = tree.query_ball_point(frontier, eps)
        hits = np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]))
        new = hits[allowed[hits] & ~grown[hits]]
        grown[new] = True
        frontier = pts[low[new]]
    taken |= grown
    return low[grown]


def _smooth_components(
    pts: np.ndarray, cols: np.ndarray, views: np.ndarray, eps: float, smooth_deg: float, color_tol: float
) -> np.ndarray:
    """Connected components of the neighbour graph whose edges join smooth, similarly coloured points."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    normals = estimate_normals(pts, k=20, viewpoints=views)
    pairs = cKDTree(pts).query_pairs(eps, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    keep = ((normals[i] * normals[j]).sum(axis=1) > np.cos(np.radians(smooth_deg))) & (
        np.abs(cols[i] - cols[j]).max(axis=1) < color_tol
    )
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(len(pts), len(pts)))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _inside_table(pts: np.ndarray, table: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """True where a point's projection on the table plane falls inside the convex hull of the table points."""
    from scipy.spatial import ConvexHull, QhullError

    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    flat = lambda p: np.stack([p @ u, p @ v], axis=1)
    try:
        equations = ConvexHull(flat(table)).equations  # outward half-planes a . p + b <= 0 inside
    except (QhullError, ValueError):  # a degenerate table outline: keep everything
        return np.ones(len(pts), dtype=bool)
    return np.all(flat(pts) @ equations[:, :2].T + equations[:, 2] <= 1e-9, axis=1)


def merge_stacked(scene: TableScene, cluster: Cluster) -> Cluster:
    """``cluster`` joined with every other cluster of ``scene`` whose footprint centre (its centroid seen
    from above the table) lies inside ``cluster``'s footprint, or the other way round.

    On a table objects stand side by side, not on top of each other, so pieces stacked above one
    footprint are one object split where the camera saw too little of it (a wine glass's thin stem
    leaves its bowl and foot apart).
    """
    from scipy.spatial import ConvexHull, QhullError

    normal = scene.plane[:3]
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)

    def footprint(c: Cluster):
        flat = np.stack([c.points @ u, c.points @ v], axis=1)
        try:
            return ConvexHull(flat).equations, flat.mean(axis=0)
        except (QhullError, ValueError):
            return None, flat.mean(axis=0)

    def inside(equations, point) -> bool:
        return equations is not None and bool(np.all(equations[:, :2] @ point + equations[:, 2] <= 0))

    hull, centre = footprint(cluster)
    parts = [cluster]
    for other in scene.clusters:
        if other is cluster:
            continue
        other_hull, other_centre = footprint(other)
        if inside(hull, other_centre) or inside(other_hull, centre):
            parts.append(other)
    if len(parts) == 1:
        return cluster
    points = np.concatenate([c.points for c in parts])
    height = points @ normal + scene.plane[3]
    top = float(height.max())
    mean = points.mean(axis=0)
    return Cluster(
        points, np.concatenate([c.colors for c in parts]), np.concatenate([c.viewpoints for c in parts]), mean,
        mean - (height.mean() - 0.5 * top) * normal, top,
    )


def pick_cluster(scene: TableScene, target: np.ndarray | None = None) -> Cluster:
    """The cluster whose centroid is nearest ``target`` (mm), or the largest one.

    Raises:
        InvalidMeshError: the scene has no clusters.
    """
    if not scene.clusters:
        raise InvalidMeshError("scene: no object found on the table (no cluster above the plane)")
    if target is None:
        return scene.clusters[0]
    d = [np.linalg.norm(c.centroid - target) for c in scene.clusters]
    return scene.clusters[int(np.argmin(d))]


__all__ = ["Cluster", "TableScene", "frames_to_points", "merge_stacked", "pick_cluster", "segment_table"]
