"""RGB-D frames of an object on a table -> its views fused -> a closed ``ObjectModel`` (:func:`reconstruct_frames`).

Points in the world frame -> table plane removed (RANSAC) -> objects segmented -> the chosen object's views
fused (known poses, ICP refinement) -> the surface step of :mod:`~perception.reconstruct.surface`, closed
where no camera saw it (the bottom on the table) from the space the frames carved
(:func:`~perception.reconstruct.carving.carve`), so the model stands in for a CAD mesh: watertight, with
the CAD mesh's centre and size. Units are millimetres; the same input and seed give the same bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from perception.errors import InvalidMeshError
from perception.geometry import ObjectModel, rescale
from perception.reconstruct.carving import carve
from perception.reconstruct.points import MIN_POINTS, estimate_normals
from perception.reconstruct.surface import close_holes, points_to_model
from perception.reconstruct.tabletop import (
    Cluster,
    TableScene,
    _check_pixel,
    check_voxel,
    frames_to_points,
    merge_stacked,
    pick_cluster,
    pick_pixel,
    segment_table,
)

log = logging.getLogger(__name__)

#: A closed reconstruction with more than this fraction of its vertices outside the carved space (grown
#: by two voxels) has leaked: Poisson extrapolated a thin shell seen on one side (:func:`reconstruct_frames`).
LEAK_FRACTION = 0.01


def refine_views(
    clouds: list[np.ndarray], *, max_distance_mm: float = 2.0, max_rotation_deg: float = 2.0
) -> list[np.ndarray]:
    """ICP-refine each view's points (already aligned by known poses, world mm) onto the union of the
    previous ones; returns the 4 x 4 corrections (identity for the first view).

    Point-to-plane ICP (Open3D) with correspondences within ``max_distance_mm``: on virtual OAK captures
    with exact poses it stays within 0.2 mm of the identity, where point-to-point ICP within 5 mm drifted
    by 1-1.5 mm and tripled the surface error (``benchmarks/reconstruction.py``). Corrections that move the first
    view's centroid by more than ``max_distance_mm`` or turn by more than ``max_rotation_deg`` are refused
    (identity): poses are known, ICP only polishes. ICP runs about that centroid, so where the world origin lies
    (a camera's own frame puts the object half a metre away) changes neither its precision nor what counts as a
    small correction.
    """
    if not clouds:
        return []
    reg = o3d.pipelines.registration
    first = np.asarray(clouds[0], dtype=np.float64).reshape(-1, 3)
    finite = first[np.isfinite(first).all(axis=1)]
    centre = finite.mean(axis=0) if len(finite) else np.zeros(3)  # a stray NaN must not reach every correction
    corrections = [np.eye(4)]
    reference = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clouds[0] - centre))
    for i, pts in enumerate(clouds[1:], start=1):
        local = pts - centre
        moving = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(local))
        reference.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        result = reg.registration_icp(
            moving, reference, max_distance_mm, np.eye(4), reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=30),
        )
        t = np.asarray(result.transformation)
        angle = np.degrees(np.arccos(np.clip((np.trace(t[:3, :3]) - 1) / 2, -1.0, 1.0)))
        if result.fitness < 0.05 or np.linalg.norm(t[:3, 3]) > max_distance_mm or angle > max_rotation_deg:
            log.info("view %d: ICP correction refused (fitness %.2f, %.2f mm, %.2f deg)", i, result.fitness,
                     np.linalg.norm(t[:3, 3]), angle)
            t = np.eye(4)
        # Open3D sums over threads in no fixed order: the last bits of t vary from run to run.
        t = np.round(t, 9)
        reference.points.extend(o3d.utility.Vector3dVector(local @ t[:3, :3].T + t[:3, 3]))
        world = t.copy()  # R (p - c) + t + c = R p + (t + c - R c)
        world[:3, 3] = t[:3, 3] + centre - t[:3, :3] @ centre
        corrections.append(world)
    return corrections


@dataclass
class Reconstruction:
    """What :func:`reconstruct_frames` built: the model and the intermediate data (for figures and checks).

    Attributes:
        model: the reconstructed object, in world mm unless ``size_mm`` was given.
        points, normals: (N, 3) the fused object points and their oriented normals, world mm.
        scenes: the segmented scene of each frame.
        corrections: the ICP correction (4 x 4) applied to each view.
        support: (M, 3) the points added where no camera saw the surface (:meth:`~perception.reconstruct.carving.Carving.boundary`), mm.
        picked: the index of the object in the first view's clusters (``scenes[0].clusters``).
        object: the first view's cluster of the object as reconstructed (stacked pieces joined): its size
            (:attr:`~perception.reconstruct.tabletop.Cluster.size_mm`) and warnings.
        warnings: what the views could not settle (objects they could not separate, a target pixel on no
            object), plain sentences; empty when all is clear.
    """

    model: ObjectModel
    points: np.ndarray
    normals: np.ndarray
    scenes: list[TableScene]
    corrections: list[np.ndarray]
    support: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    picked: int = 0
    object: Cluster | None = None
    warnings: list[str] = field(default_factory=list)


#: A closed reconstruction has no real openings: its holes of up to this many edges (about 20 mm across at the
#: carving's 2 mm voxels) are closed with a fan, as the surface clean-up does those of up to 16.
CLOSED_HOLE_EDGES = 32
#: The warning of a closed reconstruction that still is not watertight.
NOT_WATERTIGHT = ("the closed surface came out with holes or mixed winding (not watertight); contours through "
                  "them may open")


def reconstruct_frames(
    frames,
    *,
    target: np.ndarray | None = None,
    target_pixel: tuple[float, float] | None = None,
    name: str = "capture",
    label: str | None = None,
    size_mm: float | None = None,
    icp: bool = True,
    voxel_mm: float = 2.0,
    poisson_depth: int = 7,
    density_trim: float | None = None,
    max_depth_mm: float = 1500.0,
    roi_mm: float | None = 400.0,
    cluster_eps_mm: float = 8.0,
    method: str = "euclidean",
    close: bool = True,
    drop_flying: bool = False,
    seed: int = 0,
    **surface_kwargs,
) -> Reconstruction:
    """RGB-D frames of one object on a table (poses in ``frame.pose``) -> a reconstructed ``ObjectModel``.

    Per frame: points in the world frame, table removed, the cluster nearest ``target`` (world mm;
    default: the first frame's largest cluster, then the nearest to it) kept, with the pieces stacked
    above its footprint (:func:`~perception.reconstruct.tabletop.merge_stacked`). ``target_pixel`` (column,
    row of the first frame) instead picks the object that pixel shows
    (:func:`~perception.reconstruct.tabletop.pick_pixel`). Normals are estimated in each view and turned towards its
    camera, the views ICP-refined onto each other, outliers removed, and a Poisson surface
    (``poisson_depth``) built; ``size_mm=None`` keeps world millimetres, else the model is scaled like
    ``load_object``'s.

    ``close``: the surface is closed where no camera saw it, as the object is: the faces of the space
    the frames left uncarved (:func:`~perception.reconstruct.carving.carve`) that no observed point explains (the bottom on the table,
    the inside of a mug below the sight lines) join the points (:attr:`Reconstruction.support`). Should
    Poisson still leak (a thin shell, a spoon, whose two sides lie within a few Poisson cells: phantom
    sheets outside the carved space), the surface is built from the faces of the carved space alone,
    closed by construction and a voxel coarser. ``close=False`` keeps the seen points alone; pass
    ``density_trim=1.0`` then to cut away Poisson's extrapolation (an open surface, as before).
    ``method`` is the segmentation of :func:`~perception.reconstruct.tabletop.segment_table` (``"smooth"`` for cluttered real scenes).
    With a ``target``, only points within ``roi_mm`` of it are segmented (speed; ``None``: all).
    ``drop_flying``: leave out the flying pixels at depth edges
    (:func:`~perception.reconstruct.tabletop.flying_pixels`; for real depth cameras).

    Raises:
        InvalidMeshError: no depth, too few points for a table (e.g. a wrong depth scale), no table, no object,
            or no surface.
        InvalidArgumentError: a ``target_pixel`` outside the first frame or on neither depth nor table, or
            ``voxel_mm`` outside :data:`~perception.reconstruct.tabletop.VOXEL_MM_RANGE` (0: no down-sampling).
    """
    voxel_mm = check_voxel(voxel_mm, name)  # a bad setting fails before any work
    frames = list(frames)
    if not frames:
        raise InvalidMeshError(f"{name}: no frames to reconstruct from")
    if target_pixel is not None:
        _check_pixel(frames[0], target_pixel)  # a bad pixel fails before any work
    scenes, picked = [], []
    index, warnings = 0, []
    for i, frame in enumerate(frames):
        pts, cols, views = frames_to_points([frame], max_depth_mm=max_depth_mm, drop_flying=drop_flying)
        if target is not None and roi_mm is not None:  # only the neighbourhood of the object matters
            near = np.linalg.norm(pts - target, axis=1) <= roi_mm
            if near.sum() >= 3 * MIN_POINTS:
                pts, cols, views = pts[near], cols[near], views[near]
        scene = segment_table(
            pts, cols, views, voxel_mm=voxel_mm, cluster_eps_mm=cluster_eps_mm, method=method, seed=seed + i,
            name=f"{name} ({frame.name})",
        )
        if i == 0 and target_pixel is not None:
            index, warnings = pick_pixel(scene, frame, target_pixel)
            chosen = scene.clusters[index]
        else:
            chosen = pick_cluster(scene, target)
            index = index if i else next(k for k, c in enumerate(scene.clusters) if c is chosen)
        cluster = merge_stacked(scene, chosen)
        if i == 0:
            first = cluster
            warnings = warnings + [f"object {index}: {w}" for w in cluster.warnings]
        if target is None:
            target = cluster.centroid
        scenes.append(scene)
        picked.append(cluster)
    clouds = [c.points for c in picked]
    corrections = refine_views(clouds) if icp and len(clouds) > 1 else [np.eye(4)] * len(clouds)
    points = np.concatenate([p @ t[:3, :3].T + t[:3, 3] for p, t in zip(clouds, corrections)])
    # Normals per view, then fused: one view sees one side of a thin wall, the fused cloud both sides
    # within a few millimetres, where a shared neighbourhood would mix them.
    # Each view centred on its centroid: Open3D's covariances come from raw moments, which lose their precision
    # on points far from the origin (normals do not depend on the translation).
    normals = np.concatenate([
        estimate_normals(c.points - c.centroid, viewpoints=c.viewpoints - c.centroid) @ t[:3, :3].T
        for c, t in zip(picked, corrections)
    ])
    support, outward = np.zeros((0, 3)), np.zeros((0, 3))
    build = lambda pts, nrm: points_to_model(
        pts, nrm, name=name, label=label, size_mm=None, poisson_depth=poisson_depth, density_trim=density_trim,
        seed=seed, **surface_kwargs,
    )
    if close:
        carving = carve(frames, scenes[0].plane, points, voxel_mm=max(voxel_mm, 1.0),
                        table_mm=max(s.floor_mm for s in scenes))
        support, outward = carving.boundary(points, normals)
        model = build(np.concatenate([points, support]), np.concatenate([normals, outward]))
        outside = ~carving.contains(model.vertices, dilation=2)
        if not model.is_watertight or outside.mean() > LEAK_FRACTION:
            log.info("%s: Poisson leaked (%.1f %% of the surface outside the carved space); surface of the "
                     "carved space instead", name, 100 * outside.mean())
            support, outward = carving.boundary()
            model = build(support, outward)
        # Nothing of the object lies below the table: a Poisson sheet that does is pressed onto it.
        plane = scenes[0].plane
        height = model.vertices @ plane[:3] + plane[3]
        if (height < 0).any():
            vertices = model.vertices - np.minimum(height, 0.0)[:, None] * plane[:3]
            model = ObjectModel(vertices, model.triangles, name=name, label=label)
        if not model.is_watertight:  # a hole larger than the surface clean-up closes (a wine glass from 8 views)
            vertices, triangles = close_holes(model.vertices, model.triangles, max_edges=CLOSED_HOLE_EDGES)
            if len(triangles) > len(model.triangles):
                filled = ObjectModel(vertices, triangles, name=name, label=label)
                model = filled if filled.is_watertight else model
        if not model.is_watertight:  # rare (mixed winding: a funnel at Poisson depth 6): contours may open, say so
            warnings = warnings + [NOT_WATERTIGHT]
    else:
        model = build(points, normals)
    if size_mm is not None:
        model = rescale(model, size_mm, name=name)
        model.label = label
    for w in warnings:
        log.warning("%s: %s", name, w)
    return Reconstruction(model, points, normals, scenes, corrections, support, index, first, warnings)


__all__ = ["Reconstruction", "reconstruct_frames", "refine_views"]
