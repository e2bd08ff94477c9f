"""Tabletop scenes: RGB-D points -> the table plane -> the objects standing on it, each alone -> the one to touch.

Objects that touch are told apart by the surface between them (``method="convex"``, the default for real
captures): where two objects meet, the surface folds inwards (a concave crease) or steps (one occludes the
other), where one object's surface runs on (convex edges, smooth faces, printed colour) it does not. The
cloud is over-segmented where normals or colours jump, then neighbouring pieces are joined again where
their common border is neither concave nor a step: a two-colour drill is one object, a can lying against
it another (the locally convex connected patches of Stein et al., CVPR 2014, on points).

A piece that does not reach the table rests on something: it is joined with the object under it
(:func:`merge_stacked`), with a warning, since one view cannot tell a box resting on a box from one
object's two parts. Units are millimetres; pixels are (column, row) of a frame's image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from perception.errors import InvalidArgumentError, InvalidMeshError
from perception.reconstruct.points import MIN_POINTS, _as_points, estimate_normals

log = logging.getLogger(__name__)

#: Segmentation methods of :func:`segment_table`.
SEGMENTATION_METHODS = ("euclidean", "smooth", "convex")
#: ``method="convex"``: neighbours whose normals turn inwards by more than this are a concave crease, degrees.
CONCAVE_DEG = 10.0
#: ``method="convex"``: a neighbour more than this off a point's tangent plane is across a step (an
#: occluding edge), degrees.
STEP_DEG = 30.0
#: ``method="convex"``: two pieces are one object when less than this fraction of the neighbour pairs
#: across their border are concave or steps (measured on the GraspNet frame: 0.1 to 0.3 give the same objects)...
MERGE_FRACTION = 0.2
#: ... and at least this many pairs join them (a border of a few points is a touch, not a shared surface).
MIN_BORDER_PAIRS = 20
#: A cluster whose lowest point is more than this above the table does not stand on it: it rests on
#: another object or is a part split off one (a wine glass's bowl), mm.
FLOATING_MM = 15.0
#: A cluster larger than this (bounding-box diagonal) is no hand-held object: several objects, or an object
#: and a fixture, that the view could not separate, mm.
MAX_OBJECT_MM = 300.0
#: ``voxel_mm`` accepted by :func:`segment_table` and :func:`~perception.reconstruct.multiview.reconstruct_frames`
#: (besides 0: no down-sampling), mm. 0.1 mm is ten times finer than a depth camera resolves at table distance
#: (about 1 mm at 0.5 m), and keeps Open3D's voxel grid far from its integer limit on any scene a camera can see
#: (1e-9 mm overflowed it). At 20 mm the largest object a scene holds (:data:`MAX_OBJECT_MM`) keeps a few hundred
#: voxels of its visible side, a 150 mm can some 50, under the 100 a cluster needs: coarser grids find no object
#: (1e9 mm left RANSAC fewer than 3 points). 2 to 3 mm is the usual choice.
VOXEL_MM_RANGE = (0.1, 20.0)
#: Open3D's voxel grid indexes voxels with ``int``: a cloud may span at most this many voxels along an axis.
_MAX_VOXELS_PER_AXIS = 2**31 - 2


def check_voxel(voxel_mm, where: str = "scene") -> float:
    """``voxel_mm`` as a float: 0 (no down-sampling) or a length in :data:`VOXEL_MM_RANGE`, mm.

    Raises:
        InvalidArgumentError: not a real number, NaN, infinite, negative or outside the range; naming ``where``.
    """
    low, high = VOXEL_MM_RANGE
    number = isinstance(voxel_mm, (int, float, np.integer, np.floating)) and not isinstance(voxel_mm, bool)
    if not (number and (voxel_mm == 0 or low <= voxel_mm <= high)):  # NaN fails every comparison
        raise InvalidArgumentError(
            f"{where}: voxel_mm must be 0 (no down-sampling) or a length in [{low:g}, {high:g}] mm, got {voxel_mm!r}; "
            "2 to 3 mm suits a depth camera at table distance"
        )
    return float(voxel_mm)


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
        base_mm: smallest height above the table plane, mm (above :data:`FLOATING_MM`: it rests on something).
        size_mm: (3,) length and width of its footprint (along the footprint's principal axes) and height, mm.
        warnings: what the view could not settle about it (merged pieces, implausible size), plain sentences.
    """

    points: np.ndarray
    colors: np.ndarray
    viewpoints: np.ndarray
    centroid: np.ndarray
    center: np.ndarray
    height_mm: float
    base_mm: float = 0.0
    size_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    warnings: list[str] = field(default_factory=list)

    @property
    def diagonal_mm(self) -> float:
        """Diagonal of the box of :attr:`size_mm`, mm."""
        return float(np.linalg.norm(self.size_mm))


def _make_cluster(points: np.ndarray, colors: np.ndarray, viewpoints: np.ndarray, plane: np.ndarray) -> Cluster:
    """A cluster of ``points`` (mm) on the table ``plane``, with its centre, heights and size."""
    normal = plane[:3]
    height = points @ normal + plane[3]
    top = float(height.max())
    mean = points.mean(axis=0)
    # Prism centre: the mean's foot on the table, raised by half the height.
    center = mean - (height.mean() - 0.5 * top) * normal
    u, v = _plane_axes(normal)
    flat = np.stack([points @ u, points @ v], axis=1)
    flat = flat - flat.mean(axis=0)
    axes = np.linalg.svd(flat, full_matrices=False)[2] if len(flat) > 1 else np.eye(2)
    extent = np.ptp(flat @ axes.T, axis=0) if len(flat) else np.zeros(2)
    size = np.array([extent.max(), extent.min(), top])
    cluster = Cluster(points, colors, viewpoints, mean, center, top, float(height.min()), size)
    if cluster.diagonal_mm > MAX_OBJECT_MM:
        cluster.warnings.append(
            f"{cluster.diagonal_mm:.0f} mm across, more than a hand-held object ({MAX_OBJECT_MM:.0f} mm): "
            "probably several objects, or an object and a fixture, that this view cannot separate"
        )
    return cluster


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


#: Flying pixels (:func:`flying_pixels`): window radius, pixels, and the depth step, as a fraction of the
#: pixel's depth, by which a pixel must lie behind a nearer neighbour (and half that in front of a farther one).
FLYING_RADIUS_PX = 3
FLYING_STEP = 0.02


def flying_pixels(depth_mm: np.ndarray, *, radius_px: int = FLYING_RADIUS_PX, step: float = FLYING_STEP) -> np.ndarray:
    """(H, W) True at the *flying pixels* of a depth image: pixels that lie between a nearer and a farther
    surface: more than ``step`` x their depth behind some valid pixel and more than half that in front of
    another, within ``radius_px`` pixels. A depth camera averages across a depth edge (stereo matching windows, the
    RealSense's and the OAK's alike): the pixels along an object's silhouette take depths between the object
    and the table behind it, a ramp of points in the empty space behind the object that joins its cluster
    and makes it look longer (measured on the GraspNet frame: 5 % of the soup can's points more than 15 mm
    off its true surface, nearly all at such edges). A pixel on a surface seen edge-on (more than about 75
    degrees from the ray at 0.7 mm per pixel) meets the test too; its depth is the least reliable anyway.
    The nearer surface's own edge pixels and the background's stay; the ramp's foot (less than half a step
    above the background) stays too, within the table's tolerance. A flat surface's noise alone must
    reach 3.3 standard deviations at 0.45 m (RealSense, 2.7 mm on the GraspNet table) to meet the test."""
    from scipy import ndimage

    depth = np.asarray(depth_mm, dtype=np.float64)
    valid = depth > 0
    size = 2 * int(radius_px) + 1
    nearest = ndimage.minimum_filter(np.where(valid, depth, np.inf), size=size, mode="nearest")
    farthest = ndimage.maximum_filter(np.where(valid, depth, 0.0), size=size, mode="nearest")
    gap = step * depth
    return valid & (depth - nearest > gap) & (farthest - depth > 0.5 * gap)


def frames_to_points(
    frames, *, max_depth_mm: float = 1500.0, drop_flying: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (mm), colours and viewpoints of all valid pixels of ``frames`` (depth <= ``max_depth_mm``),
    without the flying pixels at depth edges (:func:`flying_pixels`) with ``drop_flying`` (real depth cameras;
    it also drops steep sides seen edge-on, which may split a box's side from its top in a clean synthetic view).

    Raises:
        InvalidMeshError: no frame has any depth.
    """
    pts, cols, views = [], [], []
    for frame in frames:
        keep = frame.valid & (frame.depth_mm <= max_depth_mm)
        if drop_flying:
            keep &= ~flying_pixels(frame.depth_mm)
        p, c = frame.points(keep)
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
    name: str = "scene",
) -> TableScene:
    """Find the table plane (RANSAC) and cluster what stands on it (DBSCAN), all in mm.

    The cloud is down-sampled on a ``voxel_mm`` grid (:data:`VOXEL_MM_RANGE`; 0: not down-sampled); the plane
    with the most inliers within ``plane_tolerance_mm`` is the table, refined by least squares on its inliers; its normal points
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
    ``method="convex"`` separates touching objects by the surface between them (see the module docstring):
    the ``smooth`` pieces are joined again where their border is neither concave (:data:`CONCAVE_DEG`) nor
    a step (:data:`STEP_DEG`); on the real GraspNet frame it leaves each of the 9 annotated objects in its
    own cluster (``benchmarks/reconstruction.py``). Clusters larger than :data:`MAX_OBJECT_MM` carry a warning.
    ``name`` (the capture or frame) heads the error messages.

    Raises:
        InvalidMeshError: too few points (before or after down-sampling), points spread too far for the grid,
            or no plane found.
        InvalidArgumentError: an unknown method, or ``voxel_mm`` outside :data:`VOXEL_MM_RANGE`.
    """
    if method not in SEGMENTATION_METHODS:
        raise InvalidArgumentError(
            f"{name}: unknown segmentation method {method!r}; choose one of {', '.join(SEGMENTATION_METHODS)}"
        )
    voxel_mm = check_voxel(voxel_mm, name)
    points = _as_points(points, name)
    if len(points) < 3 * MIN_POINTS:
        raise InvalidMeshError(f"{name}: only {len(points)} points with depth; cannot find a table")
    extent = float((points.max(axis=0) - points.min(axis=0)).max())
    if voxel_mm > 0 and not extent / voxel_mm <= _MAX_VOXELS_PER_AXIS:
        raise InvalidMeshError(f"{name}: the points span {extent:.3g} mm, more than {_MAX_VOXELS_PER_AXIS} voxels of "
                               f"{voxel_mm:g} mm; no table scene is that large: check the depth scale and the pose")
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
    if len(pts) < 3 * MIN_POINTS:  # RANSAC needs 3 points, and a table with objects on it far more
        raise InvalidMeshError(
            f"{name}: too few points in the capture: {len(pts)} left of {len(points)} after down-sampling on a "
            f"{voxel_mm:g} mm grid (they span {extent:.3g} mm), a table needs at least {3 * MIN_POINTS}; check the "
            "depth scale (depth units per metre) or use a finer voxel_mm"
        )
    o3d.utility.random.seed(int(seed))
    cloud.normals = o3d.utility.Vector3dVector()
    _, inliers = cloud.segment_plane(plane_tolerance_mm, 3, 1000)
    inliers = np.asarray(inliers, dtype=np.int64)
    if len(inliers) < 3:
        raise InvalidMeshError(f"{name}: no table plane found")
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
        if method in ("smooth", "convex"):
            raw = _smooth_components(
                pts[above], cols[above], views[above], cluster_eps_mm, smooth_deg, color_tolerance,
                convex=method == "convex",
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
            clusters.append(_make_cluster(pts[idx], cols[idx], views[idx], plane))
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
    pts: np.ndarray, cols: np.ndarray, views: np.ndarray, eps: float, smooth_deg: float, color_tol: float,
    *, convex: bool = False,
) -> np.ndarray:
    """Connected components of the neighbour graph whose edges join smooth, similarly coloured points.

    ``convex``: edges across a concave crease or a step are cut too, and the components are then joined
    again where their border is mostly neither (:data:`MERGE_FRACTION`, :data:`MIN_BORDER_PAIRS`).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    normals = estimate_normals(pts, k=20, viewpoints=views)
    pairs = cKDTree(pts).query_pairs(eps, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    cos = (normals[i] * normals[j]).sum(axis=1)
    keep = (cos > np.cos(np.radians(smooth_deg))) & (np.abs(cols[i] - cols[j]).max(axis=1) < color_tol)
    n = len(pts)
    if convex:
        d = pts[i] - pts[j]
        # Convex where the normals open away from each other: (n_i - n_j) . (p_i - p_j) > 0.
        folded = cos < np.cos(np.radians(CONCAVE_DEG))
        convex_fold = folded & (((normals[i] - normals[j]) * d).sum(axis=1) > 0)
        concave = folded & ~convex_fold
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        off = np.maximum(np.abs((normals[i] * unit).sum(axis=1)), np.abs((normals[j] * unit).sum(axis=1)))
        # A pair off each other's tangent planes is a step (one surface occluding another behind it). NaN
        # (coincident points) counts as a step. (Exempting sharp convex folds, > 45 or 70 degrees, joined the
        # GraspNet cup to its neighbour: measured, left out.)
        broken = concave | ~(off <= np.sin(np.radians(STEP_DEG)))
        keep &= ~concave
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
    labels = connected_components(graph, directed=False)[1].astype(np.int64)
    if not convex or not len(pairs):
        return labels
    a, b = labels[i], labels[j]
    across = a != b
    lo, hi, bad = np.minimum(a, b)[across], np.maximum(a, b)[across], broken[across]
    m = int(labels.max()) + 1
    border, inverse = np.unique(lo * m + hi, return_inverse=True)
    total = np.bincount(inverse, minlength=len(border))
    broken_count = np.bincount(inverse, weights=bad.astype(np.float64), minlength=len(border))
    join = (total >= MIN_BORDER_PAIRS) & (broken_count < MERGE_FRACTION * total)
    pieces = coo_matrix((np.ones(int(join.sum())), (border[join] // m, border[join] % m)), shape=(m, m))
    return connected_components(pieces, directed=False)[1][labels].astype(np.int64)


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
    """``cluster`` joined with every other cluster of ``scene`` that rests on it or that it rests on: one of
    the two does not reach the table (its lowest point more than :data:`FLOATING_MM` above it) and the
    footprint centre of one (its centroid seen from above the table) lies inside the other's footprint.

    Objects on a table stand on it, side by side; a piece that floats above another's footprint is one
    object split where the camera saw too little of it (a wine glass's thin stem leaves its bowl and foot
    apart), or an object resting on another (a box on a box): one view cannot tell which, so the pieces
    are joined and the result says so in :attr:`Cluster.warnings`. Neighbours that both stand on the table
    are never joined.
    """
    from scipy.spatial import ConvexHull, QhullError

    normal = scene.plane[:3]
    u, v = _plane_axes(normal)

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
        if other is cluster or max(other.base_mm, cluster.base_mm) <= FLOATING_MM:
            continue
        other_hull, other_centre = footprint(other)
        if inside(hull, other_centre) or inside(other_hull, centre):
            parts.append(other)
    if len(parts) == 1:
        return cluster
    merged = _make_cluster(
        np.concatenate([c.points for c in parts]), np.concatenate([c.colors for c in parts]),
        np.concatenate([c.viewpoints for c in parts]), scene.plane,
    )
    merged.warnings.insert(0, (
        f"joined from {len(parts)} pieces stacked on one footprint (one does not reach the table): one object "
        "split where the camera saw little of it, or objects resting on each other, which one view cannot tell apart"
    ))
    return merged


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


def _check_pixel(frame, pixel) -> tuple[float, float]:
    """``pixel`` as (u, v) floats, checked to lie in ``frame``'s image.

    Raises:
        InvalidArgumentError: not two finite numbers inside the image.
    """
    k = frame.intrinsics
    try:
        u, v = (float(x) for x in pixel)
    except (TypeError, ValueError):
        raise InvalidArgumentError(f"target pixel {pixel!r}: expected two numbers U,V (column, row)") from None
    if not (np.isfinite(u) and np.isfinite(v) and 0 <= u <= k.width - 1 and 0 <= v <= k.height - 1):
        raise InvalidArgumentError(
            f"target pixel ({u:g}, {v:g}) of {frame.name}: outside the {k.width} x {k.height} image "
            f"(U in 0..{k.width - 1}, V in 0..{k.height - 1})"
        )
    return u, v


def pixel_point(frame, pixel, plane: np.ndarray | None = None) -> np.ndarray:
    """The world point (mm) that ``frame`` saw at ``pixel`` (column u, row v): its depth where it has one,
    else where the pixel's ray meets the table ``plane`` (if given and in front of the camera).

    Raises:
        InvalidArgumentError: ``pixel`` is not two finite numbers inside the image, or it has no depth and
            no table behind it.
    """
    k = frame.intrinsics
    u, v = _check_pixel(frame, pixel)
    col, row = round(u), round(v)
    ray = np.array([(u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0])
    rot, eye = frame.pose[:3, :3], frame.pose[:3, 3]
    depth = float(frame.depth_mm[row, col]) if frame.valid[row, col] else 0.0
    if depth > 0:
        return eye + rot @ (ray * depth)
    if plane is not None:
        direction = rot @ ray
        along = float(direction @ plane[:3])
        t = -(eye @ plane[:3] + plane[3]) / along if abs(along) > 1e-12 else -1.0
        if t > 0:
            return eye + t * direction
    raise InvalidArgumentError(f"target pixel ({u:g}, {v:g}) of {frame.name}: no depth there and no table behind it")


def pick_pixel(scene: TableScene, frame, pixel) -> tuple[int, list[str]]:
    """The cluster of ``scene`` (segmented from ``frame``) that ``frame`` saw at ``pixel`` (column, row):
    the one holding the pixel's point (within three point spacings, :func:`pixel_point`), else the cluster nearest
    it, with a warning saying how far. Returns the cluster's index and the warnings.

    Raises:
        InvalidArgumentError: a bad pixel (:func:`pixel_point`).
        InvalidMeshError: the scene has no clusters.
    """
    from scipy.spatial import cKDTree

    point = pixel_point(frame, pixel, scene.plane)
    if not scene.clusters:
        raise InvalidMeshError(f"{frame.name}: no object found on the table (no cluster above the plane)")
    gaps = [float(cKDTree(c.points).query(point)[0]) for c in scene.clusters]
    best = int(np.argmin(gaps))
    spacing = float(np.median(cKDTree(scene.points).query(scene.points, k=2)[0][:, 1])) if len(scene.points) > 1 else 0.0
    if gaps[best] <= 3 * max(spacing, 1.0):
        return best, []
    u, v = (float(x) for x in pixel)
    return best, [f"pixel ({u:g}, {v:g}) is on no object; object {best}, {gaps[best]:.0f} mm from its point, was taken"]


def describe_objects(scene: TableScene, frame) -> list[dict]:
    """One plain record per cluster of ``scene``, in its order: ``index``, ``center_mm`` (prism centre,
    world), ``size_mm`` (footprint length and width, height), ``diagonal_mm``, ``pixel`` (centroid of its
    points projected into ``frame``: column, row), ``points`` and ``warnings``. JSON-ready, no NaN."""
    k = frame.intrinsics
    out = []
    for i, c in enumerate(scene.clusters):
        cam = (c.points - frame.pose[:3, 3]) @ frame.pose[:3, :3]
        front = cam[:, 2] > 0
        if front.any():
            uv = [float(np.mean(k.fx * cam[front, 0] / cam[front, 2] + k.cx)),
                  float(np.mean(k.fy * cam[front, 1] / cam[front, 2] + k.cy))]
        else:
            uv = None
        out.append({
            "index": i,
            "center_mm": [round(float(x), 1) for x in c.center],
            "size_mm": [round(float(x), 1) for x in c.size_mm],
            "diagonal_mm": round(c.diagonal_mm, 1),
            "pixel": None if uv is None else [round(x, 1) for x in uv],
            "points": len(c.points),
            "warnings": list(c.warnings),
        })
    return out


__all__ = [
    "SEGMENTATION_METHODS",
    "VOXEL_MM_RANGE",
    "Cluster",
    "TableScene",
    "check_voxel",
    "describe_objects",
    "flying_pixels",
    "frames_to_points",
    "merge_stacked",
    "pick_cluster",
    "pick_pixel",
    "pixel_point",
    "segment_table",
]
