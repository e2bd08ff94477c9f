"""Flying pixels at depth edges (:func:`perception.reconstruct.tabletop.flying_pixels`): known answers on a
synthetic tabletop seen straight down, where a window-averaging depth camera leaves ramps of mixed depths
around every box (the pixels between a box's edge and the table behind it)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from perception.camera.frame import Intrinsics, RGBDFrame
from perception.reconstruct.tabletop import flying_pixels, frames_to_points, merge_stacked, segment_table

F, W, H, TABLE_MM = 500.0, 400, 300, 500.0  # 1 px = 1 mm on the table


def _scene(boxes, ramp_px: int = 8) -> RGBDFrame:
    """Depth of axis-aligned ``boxes`` ((x0, x1, y0, y1, height) in mm, camera frame) standing on a table
    ``TABLE_MM`` in front of a camera looking straight at it, with ``ramp_px`` flying pixels beyond every
    silhouette: table pixels that near a box take depths running linearly from the box's edge to the
    table (what a window-matching depth camera leaves at a depth edge)."""
    k = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    dx, dy = (u - k.cx) / F, (v - k.cy) / F  # ray (dx, dy, 1): the depth is the ray parameter
    depth = np.full((H, W), TABLE_MM)
    for x0, x1, y0, y1, h in boxes:  # slab test against the box [x0, x1] x [y0, y1] x [TABLE - h, TABLE]
        t_lo = np.full((H, W), TABLE_MM - h)
        t_hi = np.full((H, W), TABLE_MM)
        for d, lo, hi in ((dx, x0, x1), (dy, y0, y1)):
            with np.errstate(divide="ignore"):
                a, b = lo / d, hi / d
            t_lo = np.maximum(t_lo, np.where(d != 0, np.minimum(a, b), np.where((lo <= 0) & (0 <= hi), -np.inf, np.inf)))
            t_hi = np.minimum(t_hi, np.where(d != 0, np.maximum(a, b), np.inf))
        hit = t_lo <= t_hi
        depth = np.where(hit, np.minimum(depth, t_lo), depth)
    if ramp_px:
        box = depth < TABLE_MM - 0.5
        gap, (rows, cols) = ndimage.distance_transform_edt(~box, return_indices=True)
        ramp = ~box & (gap <= ramp_px)
        edge = depth[rows, cols]
        depth = np.where(ramp, edge + (TABLE_MM - edge) * gap / (ramp_px + 1), depth)
    color = np.full((H, W, 3), 128, dtype=np.uint8)
    return RGBDFrame(color, depth.astype(np.float32), k, name="synthetic")


def _clusters(frame, drop_flying: bool, method: str = "euclidean"):
    """The objects of ``frame``, each with the pieces stacked on it (as the reconstruction takes them)."""
    points, colors, views = frames_to_points([frame], drop_flying=drop_flying)
    scene = segment_table(points, colors, views, voxel_mm=2.0, method=method)
    out = {}
    for c in scene.clusters:  # a piece stacked on an object gives the same joined cluster as the object
        merged = merge_stacked(scene, c)
        out.setdefault(tuple(np.round(merged.centroid, 3)), merged)
    return list(out.values())


def test_flying_pixels_are_the_ramps_between_a_box_and_the_table():
    box = (-40.0, 40.0, -25.0, 25.0, 40.0)
    sharp, ramped = _scene([box], ramp_px=0), _scene([box])
    assert not flying_pixels(sharp.depth_mm).any()  # a clean edge: the box's rim and the table stay
    mask = flying_pixels(ramped.depth_mm)
    mixed = (ramped.depth_mm > sharp.depth_mm.min() + 3) & (ramped.depth_mm < TABLE_MM - 3)
    # Nearly all mixed pixels go; nothing on the box top or the open table does.
    assert mask[mixed].mean() > 0.6
    top = sharp.depth_mm < TABLE_MM - 39.5
    assert not mask[top].any() and not mask[ramped.depth_mm > TABLE_MM - 0.5].any()


@pytest.mark.parametrize("method", ["euclidean", "convex"])
def test_a_box_with_flying_pixels_at_its_edges_keeps_its_size(method):
    frame = _scene([(-40.0, 40.0, -25.0, 25.0, 40.0)])
    (cluster,) = _clusters(frame, drop_flying=True, method=method)
    # Known answer 80 x 50 x 40 mm, within a few mm (the 2 mm voxels and a pixel of ramp at each end).
    assert np.allclose(cluster.size_mm, [80.0, 50.0, 40.0], atol=4.0), cluster.size_mm
    kept = _clusters(frame, drop_flying=False, method=method)
    assert max(c.size_mm[0] for c in kept) > 80.0 + 5.0  # the ramps made it longer: what the filter removes


def test_two_boxes_side_by_side_stay_apart():
    boxes = [(-70.0, -6.0, -30.0, 30.0, 40.0), (6.0, 70.0, -30.0, 30.0, 40.0)]  # 12 mm apart
    frame = _scene(boxes)
    clusters = _clusters(frame, drop_flying=True)
    assert len(clusters) == 2
    for c in clusters:  # the ramps' first two pixels (within one step of the box) stay: +2 mm a side
        assert np.allclose(c.size_mm, [64.0, 60.0, 40.0], atol=7.0), c.size_mm
    # With the ramps kept they bridge the gap (within the 8 mm clustering distance): one object of two.
    assert len(_clusters(frame, drop_flying=False)) == 1


def test_single_view_carving_stays_within_the_footprint():
    from perception.reconstruct.carving import carve

    frame = _scene([(-40.0, 40.0, -25.0, 25.0, 40.0)])
    points, colors, views = frames_to_points([frame], drop_flying=True)
    scene = segment_table(points, colors, views, voxel_mm=2.0)
    (cluster,) = _clusters(frame, drop_flying=True)

    def extent(footprint):
        carving = carve([frame], scene.plane, cluster.points, voxel_mm=2.0, footprint=footprint)
        faces, _ = carving.boundary()
        return np.ptp(faces[:, :2], axis=0)

    # The raw depth's ramps stop their rays short of the table: without the prism the solid swells into
    # them (measured: 92 x 62 mm); within it, the box's 80 x 50 mm, the ramps' foot and a voxel (88 x 58).
    inside, outside = extent(True), extent(False)
    assert np.all(inside <= np.array([80.0, 50.0]) + 9.0), inside
    assert np.all(outside >= inside + 3.0), (inside, outside)
