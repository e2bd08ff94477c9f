"""Ray-cast multi-view rendering against analytic answers (sphere depth, normals, silhouettes)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from perception import primitives
from perception.geometry import load_object
from perception.render import (
    DEFAULT_N_VIEWS,
    make_camera,
    render_views,
    surface_points,
    vertex_coverage,
    view_directions,
)


def test_view_directions_unit_distinct_deterministic_and_even():
    d = view_directions(50)
    assert d.shape == (50, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.array_equal(d, view_directions(50))
    # Evenly spread: the centroid is near the centre, and no two directions coincide.
    assert np.linalg.norm(d.mean(axis=0)) < 0.02
    gaps = np.linalg.norm(d[:, None] - d[None], axis=2) + 10 * np.eye(50)
    assert gaps.min() > 0.3
    with pytest.raises(ValueError):
        view_directions(0)


def test_sphere_depth_normals_and_silhouette_match_the_analytic_sphere():
    radius = 50.0
    model = primitives.sphere(radius, 5)
    (view,) = render_views(model, directions=np.array([[0.3, -0.5, 0.8]]), width=96, height=96)
    cam = view.camera
    # Silhouette area: a disc of radius R (within the faceting of the icosphere).
    area = view.mask.sum() * cam.pixel_mm**2
    assert area == pytest.approx(np.pi * radius**2, rel=0.02)
    # Nearest point: the image plane is distance_mm from the centre, the sphere's front at R.
    assert view.depth[view.mask].min() == pytest.approx(cam.distance_mm - radius, abs=0.05)
    # Exact barycentric points: on the ray of their pixel, and on the sphere up to faceting.
    rays = cam.rays().reshape(96, 96, 6)[view.mask]
    points = surface_points(model, view)
    on_ray = rays[:, :3] + view.depth[view.mask][:, None] * rays[:, 3:]
    np.testing.assert_allclose(points, on_ray, atol=1e-3)
    assert np.abs(np.linalg.norm(points, axis=1) - radius).max() < 0.05
    # Interpolated normals are radial; the headlight is |cos| of the view angle.
    analytic = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((view.normal[view.mask] * analytic).sum(1), -1, 1))).max() < 1.0
    np.testing.assert_allclose(view.intensity[view.mask], np.abs(analytic @ cam.forward), atol=0.02)
    # Projection is the inverse of the ray set-up.
    rows, cols = np.nonzero(view.mask)
    np.testing.assert_allclose(cam.project(points), np.column_stack([cols, rows]), atol=1e-3)


def test_background_and_barycentric_conventions():
    model = primitives.torus()
    views = render_views(model, n_views=3, width=40, height=30)
    assert len(views) == 3
    for view in views:
        assert view.depth.shape == (30, 40) and view.normal.shape == (30, 40, 3)
        assert view.color is None
        assert (view.triangle_ids[~view.mask] == -1).all() and (view.triangle_ids[view.mask] >= 0).all()
        np.testing.assert_allclose(view.barycentric[view.mask].sum(axis=1), 1.0, atol=1e-5)
        assert (view.barycentric[view.mask] >= -1e-6).all()
        assert (view.depth[~view.mask] == 0).all() and (view.intensity[~view.mask] == 0).all()
        for array in (view.depth, view.normal, view.intensity, view.barycentric):
            assert np.isfinite(array).all()


def test_colour_is_interpolated_from_vertex_colours():
    sphere = primitives.sphere(40.0, 4)
    colors = np.where(sphere.vertices[:, [0]] > 0, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    model = type(sphere)(sphere.vertices, sphere.triangles, name="two-tone", vertex_colors=colors)
    (view,) = render_views(model, directions=np.array([[0.0, 0.0, 1.0]]), width=64, height=64)
    points = surface_points(model, view)
    rgb = view.color[view.mask]
    far_right, far_left = points[:, 0] > 5, points[:, 0] < -5
    assert far_right.sum() > 100 and far_left.sum() > 100
    assert np.abs(rgb[far_right] - [1, 0, 0]).max() < 1e-6
    assert np.abs(rgb[far_left] - [0, 0, 1]).max() < 1e-6
    # Colours blend only across the triangles that straddle x = 0.
    assert ((rgb[:, 0] > 0) & (rgb[:, 2] > 0)).any()


def test_default_views_see_every_vertex_of_the_test_shapes():
    for model in (primitives.torus(), primitives.cylinder(), _catalogue("ring")):
        assert (vertex_coverage(model, render_views(model)) > 0).all(), model.name


@pytest.mark.parametrize("name", ["bottle", "box", "funnel", "hammer", "spoon", "wineglass"])
def test_default_views_reach_within_two_pixels_of_every_catalogue_vertex(name):
    # The catalogue meshes have sliver triangles below pixel size, so "a vertex of a hit triangle" is too strict;
    # what pooling needs is an observed surface point near every vertex. (The mug's inner bottom is the known
    # exception: no outside view sees into its cavity; those vertices take their nearest seen vertex's score.)
    model = _catalogue(name)
    views = render_views(model)
    hits = np.concatenate([surface_points(model, v) for v in views])
    gaps, _ = cKDTree(hits).query(model.vertices)
    assert gaps.max() < 2 * views[0].camera.pixel_mm


def test_bowl_only_misses_sub_pixel_triangles():
    # The bowl's fan at its poles has triangles far below one pixel: those vertices may be missed, but every
    # missed vertex lies within two pixels of a seen one (pooling gives it that neighbour's score).
    model = primitives.hollow_hemisphere()
    views = render_views(model, n_views=DEFAULT_N_VIEWS)
    seen = vertex_coverage(model, views) > 0
    assert seen.mean() > 0.98
    missed = model.vertices[~seen]
    gaps = np.linalg.norm(missed[:, None] - model.vertices[seen][None], axis=2).min(axis=1)
    assert gaps.max() < 2 * views[0].camera.pixel_mm


def test_real_mesh_is_fully_covered(shrec07):
    model = load_object(shrec07 / "Octopus" / "121.off")
    assert (vertex_coverage(model, render_views(model)) > 0).all()


def test_camera_frames_the_object():
    model = primitives.cylinder()
    cam = make_camera(model, np.array([0.0, 0.0, 1.0]), 32, 32)
    assert np.allclose(np.cross(cam.right, cam.up), -cam.forward)
    corners = np.array(np.meshgrid(*model.bounds.T, indexing="ij")).reshape(3, -1).T
    pix = cam.project(corners)
    assert (pix >= -0.5).all() and (pix <= 31.5).all()


def _catalogue(name: str):
    shapes = pytest.importorskip("perception.shapes")
    return shapes.make_object(name, 0)
