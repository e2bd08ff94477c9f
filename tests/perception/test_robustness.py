"""Meshes that crash or hang pymeshlab, inverted winding, mutation, extreme coordinates.

Every mesh is built here. Each reproducer must end in this process with finite output or a project
exception; where the answer is known by hand (angle deficits, analytic spheres) the output is checked too.
"""

from __future__ import annotations

import logging
import os

import numpy as np
import open3d as o3d
import pytest

from perception import curvature, primitives
from perception.errors import InvalidArgumentError, InvalidMeshError, VisuotactileError
from perception.geometry import ObjectModel, load_object, normalize
from perception.render import render_views
from perception.saliency import saliency

R_MM = 43.0


def write_off(path, vertices, triangles) -> str:
    lines = ["OFF", f"{len(vertices)} {len(triangles)} 0"]
    lines += [" ".join(repr(float(x)) for x in v) for v in vertices]
    lines += ["3 " + " ".join(str(int(i)) for i in t) for t in triangles]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def bowtie() -> tuple[np.ndarray, np.ndarray]:
    """Two regular tetrahedra (edge 2 sqrt 2) sharing vertex 0, both wound outward."""
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
    v = np.vstack([v, 2 * v[0] - v[1:]])
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    return v, np.vstack([f, np.where(f == 0, 0, f + 3)[:, ::-1]])


def merged_spheres(offset_mm: float = 30.0) -> tuple[np.ndarray, np.ndarray, int]:
    """Two overlapping spheres (R_MM) joined into one closed, edge-manifold, consistently wound surface by
    replacing a triangle of each with a three-sided tube between them: it intersects itself. Returns the
    vertices, triangles and the vertex count of one sphere."""
    s = primitives.sphere(R_MM, 3)
    va, t = s.vertices, s.triangles
    vb = va + [offset_mm, 0.3, 0.2]
    n = len(va)
    ia = int(np.argmax(va[t].mean(axis=1)[:, 0]))
    ib = int(np.argmin(vb[t].mean(axis=1)[:, 0]))
    a, b = t[ia], t[ib] + n
    b_reversed = [b[0], b[2], b[1]]
    tube = []
    for i in range(3):
        j = (i + 1) % 3
        tube += [[a[i], a[j], b_reversed[j]], [a[i], b_reversed[j], b_reversed[i]]]
    triangles = np.vstack([np.delete(t, ia, 0), np.delete(t, ib, 0) + n, tube])
    return np.vstack([va, vb]), triangles, n


def check_finite(c) -> None:
    for field in (c.mean, c.gaussian, c.k1, c.k2, c.dir1, c.dir2):
        assert np.isfinite(field).all()


def warned(caplog, text: str) -> bool:
    return any(text in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)


# ------------------------------------------------------------------------------ native crashes and hangs
def test_bowtie_loads_and_mesh_saliency_survives_the_abort(tmp_path, caplog):
    model = load_object(write_off(tmp_path / "bowtie.off", *bowtie()), size_mm=None)
    assert model.is_watertight  # the edge check passes; the shared vertex is what pymeshlab cannot take
    with caplog.at_level(logging.WARNING):
        sal = saliency(model, "mesh")
    assert np.isfinite(sal.scores).all() and sal.scores.shape == (7,)
    assert warned(caplog, "numpy discrete estimator")
    # The fallback's Gaussian curvature by hand: angle deficit / mixed area. Each outer vertex has three
    # 60-degree corners (deficit pi) and a third of three equilateral faces of area 2 sqrt 3; the shared
    # vertex has six corners (deficit 0).
    gaussian = model.curvature.gaussian
    assert gaussian[0] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(gaussian[1:], np.pi / (2 * np.sqrt(3)), rtol=1e-12)


def test_a_crash_inside_any_estimate_falls_back_in_this_process(monkeypatch, caplog):
    vertices, triangles, n = merged_spheres()
    model = ObjectModel(vertices, triangles, name="merged")
    assert model.is_watertight and model.to_open3d().is_self_intersecting()
    # Whatever pymeshlab does with it, the estimate runs in a child: make it die the way the issue saw.
    monkeypatch.setattr(curvature, "_estimate", lambda *args: os.abort())
    with caplog.at_level(logging.WARNING):
        c = model.compute_curvature("quadric")
    check_finite(c)
    assert warned(caplog, "crashed")
    # Away from the overlap and the tube the fallback still measures the sphere: H = 1/R, K = 1/R^2.
    far = np.flatnonzero(vertices[:n, 0] < -0.5 * R_MM)
    assert np.abs(c.mean[far] * R_MM - 1).max() < 0.05
    assert np.abs(c.gaussian[far] * R_MM**2 - 1).max() < 0.1


def test_self_intersecting_closed_surface_gives_finite_curvature_everywhere():
    vertices, triangles, _ = merged_spheres()
    model = ObjectModel(vertices, triangles, name="merged")
    for method in curvature.CURVATURE_METHODS:
        check_finite(model.compute_curvature(method))
    assert np.isfinite(saliency(model, "mesh").scores).all()


def test_closed_cube_with_an_unused_vertex_survives_the_segfault(tmp_path, caplog):
    box = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 10.0)
    vertices = np.vstack([np.asarray(box.vertices), [[5.0, 5.0, 5.0]]])
    path = write_off(tmp_path / "cube.off", vertices, np.asarray(box.triangles))
    model = load_object(path, repair=False, size_mm=None)
    assert model.n_vertices == 9
    with caplog.at_level(logging.WARNING):
        c = model.curvature
    check_finite(c)
    assert warned(caplog, "cube")
    assert c.mean[8] == 0 and c.gaussian[8] == 0  # the unused vertex: no area, no curvature
    # Every corner of a cube: three right angles, deficit pi/2 > 0; convex, so H > 0.
    assert (c.gaussian[:8] > 0).all() and (c.mean[:8] > 0).all()


def test_scale_quadric_on_a_box_survives_the_abort(caplog):
    box = o3d.geometry.TriangleMesh.create_box(1, 1, 1)
    check_finite(load_object(box).compute_curvature("scale_quadric"))
    unit_box = ObjectModel(np.asarray(box.vertices), np.asarray(box.triangles), name="unit box")
    with caplog.at_level(logging.WARNING):
        c = unit_box.compute_curvature("scale_quadric")  # aborts pymeshlab (2025.7)
    check_finite(c)
    assert warned(caplog, "unit box")
    assert (c.gaussian > 0).all()  # every corner of a box is convex: deficit pi/2


def test_scale_quadric_hang_on_a_tetrahedron_is_cut_and_falls_back(monkeypatch, caplog):
    monkeypatch.setattr(curvature, "CHILD_TIMEOUT_S", 1.0)
    monkeypatch.setattr(curvature, "CHILD_TIMEOUT_PER_VERTEX_S", 0.0)
    tetra = o3d.geometry.TriangleMesh.create_tetrahedron(radius=1.0)
    model = ObjectModel(np.asarray(tetra.vertices), np.asarray(tetra.triangles), name="tetra")
    with caplog.at_level(logging.WARNING):
        c = model.compute_curvature("scale_quadric")
    assert warned(caplog, "timed out")
    # Regular tetrahedron: deficit pi at each vertex over a mixed area of one face (three thirds).
    edge = np.linalg.norm(model.vertices[0] - model.vertices[1])
    np.testing.assert_allclose(c.gaussian, np.pi / (np.sqrt(3) / 4 * edge**2), rtol=1e-9)


# ------------------------------------------------------------------------- the numpy estimators vs peers
def _pymeshlab_normals(vertices, triangles, mode):
    ms = curvature._meshset(vertices, triangles)
    ms.compute_normal_per_vertex(weightmode=mode)
    return np.asarray(ms.current_mesh().vertex_normal_matrix())


@pytest.mark.parametrize("method", ["angle", "area", "max", "uniform"])
def test_numpy_normals_equal_pymeshlabs(method):
    rng = np.random.default_rng(4)
    s = primitives.sphere(50.0, 3)
    jittered = s.vertices * rng.uniform(0.8, 1.2, (s.n_vertices, 1))  # irregular: weightings differ
    from perception.isolate import run_isolated

    peer = run_isolated(
        _pymeshlab_normals, jittered, s.triangles, curvature._PYMESHLAB_NORMAL_MODES[method], timeout_s=60
    )
    ours = curvature.vertex_normals(jittered, s.triangles, method)
    np.testing.assert_allclose(ours, peer, atol=1e-12)


def test_numpy_discrete_curvature_equals_pymeshlabs_and_the_torus():
    torus = primitives.torus(50.0, 20.0, n_major=64, n_minor=32)
    rng = np.random.default_rng(5)
    jittered = torus.vertices + rng.normal(0.0, 0.3, torus.vertices.shape)
    peer = curvature.run_isolated(curvature._estimate, jittered, torus.triangles, "discrete", "t", timeout_s=60)
    mean, gaussian = curvature.discrete_curvature(
        jittered, torus.triangles, curvature.vertex_normals(jittered, torus.triangles)
    )
    # pymeshlab accumulates in single precision in places: agreement to 1e-5 of the range.
    assert np.abs(mean - peer[0]).max() < 1e-5 * np.abs(peer[0]).max()
    assert np.abs(gaussian - peer[1]).max() < 1e-5 * np.abs(peer[1]).max()
    _, true_mean, true_gaussian = primitives.analytic_torus(torus.vertices, 50.0, 20.0)
    mean, gaussian = curvature.discrete_curvature(torus.vertices, torus.triangles, torus.vertex_normals)
    assert np.abs(mean - true_mean).max() < 0.02 * np.abs(true_mean).max()
    assert np.abs(gaussian - true_gaussian).max() < 0.05 * np.abs(true_gaussian).max()


def test_repair_equals_pymeshlabs_clean_up():
    s = primitives.sphere(30.0, 2)
    v = np.vstack([s.vertices, s.vertices[:5], [[0.0, 0.0, 0.0]], [[-0.0, 0.0, 0.0]]])  # duplicates, unused
    n = s.n_vertices
    t = np.vstack(
        [
            s.triangles,
            s.triangles[:3],  # duplicate faces
            np.roll(s.triangles[3:4], 1, axis=1),  # the same face, another starting corner
            [[0, 1, n]],  # degenerate: vertex n is a copy of vertex 0
            [[0, 1, 1]],  # repeated index
            s.triangles[5:7] % 5 + n,  # faces on the duplicate vertices
        ]
    )
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=t))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_unreferenced_vertices()
    from perception.meshio import repair

    ours_v, ours_t, _ = repair(v, t, None, "test")
    np.testing.assert_array_equal(ours_v, ms.current_mesh().vertex_matrix())
    # The same faces with the same winding (pymeshlab re-orders the face list when it drops duplicates).
    np.testing.assert_array_equal(canonical(ours_t), canonical(ms.current_mesh().face_matrix()))
    assert len(ours_t) == s.n_triangles + 2
    # Faces on the same vertices wound both ways: pymeshlab keeps either, we keep the first, by hand.
    _, kept, _ = repair(s.vertices, np.vstack([s.triangles, s.triangles[:1, ::-1]]), None, "test")
    np.testing.assert_array_equal(kept, s.triangles)


def canonical(triangles: np.ndarray) -> np.ndarray:
    """Faces rotated to start at their smallest index (winding kept), rows sorted."""
    t = np.asarray(triangles)
    shift = np.argmin(t, axis=1)
    rows = np.stack([np.roll(row, -k) for row, k in zip(t, shift)])
    return rows[np.lexsort(rows.T[::-1])]


# ----------------------------------------------------------------------------------------- winding
def _outward_fraction(model: ObjectModel) -> float:
    return float(np.mean(np.einsum("ij,ij->i", model.vertex_normals, model.vertices - model.center) > 0))


def test_inward_wound_sphere_loads_outward(tmp_path):
    s = primitives.sphere(R_MM, 3)
    model = load_object(write_off(tmp_path / "inward.off", s.vertices, s.triangles[:, ::-1]), size_mm=None)
    np.testing.assert_array_equal(model.triangles, s.triangles)
    assert _outward_fraction(model) == 1.0


def test_partly_flipped_closed_mesh_is_made_consistent_and_outward(tmp_path):
    s = primitives.sphere(R_MM, 3)
    t = s.triangles.copy()
    flip = np.random.default_rng(0).random(len(t)) < 0.3
    t[flip] = t[flip][:, ::-1]
    model = load_object(write_off(tmp_path / "mixed.off", s.vertices, t), size_mm=None)
    assert model.is_watertight
    np.testing.assert_array_equal(model.triangles, s.triangles)


def test_hollow_ball_keeps_its_inner_wall_facing_the_cavity(tmp_path):
    s = primitives.sphere(R_MM, 2)
    v = np.vstack([s.vertices, 0.5 * s.vertices])
    right = np.vstack([s.triangles, s.triangles[:, ::-1] + s.n_vertices])  # inner wall faces the centre
    assert np.array_equal(load_object(write_off(tmp_path / "a.off", v, right), size_mm=None).triangles, right)
    wrong = np.vstack([s.triangles[:, ::-1], s.triangles + s.n_vertices])  # both walls the wrong way
    assert np.array_equal(load_object(write_off(tmp_path / "b.off", v, wrong), size_mm=None).triangles, right)


def test_open_inward_wound_hemisphere_is_turned_outward(tmp_path):
    s = primitives.sphere(R_MM, 3)
    cap = s.triangles[s.vertices[s.triangles].mean(axis=1)[:, 2] > 0]
    model = load_object(write_off(tmp_path / "cap.off", s.vertices, cap[:, ::-1]), size_mm=None)
    assert not model.is_watertight
    normals = model.vertex_normals
    assert (np.einsum("ij,ij->i", normals, model.vertices) > 0).all()


def test_orientation_can_be_left_alone(tmp_path):
    s = primitives.sphere(R_MM, 2)
    path = write_off(tmp_path / "inward.off", s.vertices, s.triangles[:, ::-1])
    np.testing.assert_array_equal(load_object(path, orient=False, size_mm=None).triangles, s.triangles[:, ::-1])


# ---------------------------------------------------------------------------------- cached, mutable
def test_assigning_geometry_drops_every_cache():
    model = primitives.sphere(R_MM, 2)
    diagonal, normals = model.diagonal, model.vertex_normals
    _, before = model.closest_points(np.zeros((1, 3)))
    curvature_before = model.curvature.mean.copy()
    model.vertices = model.vertices * 2
    assert model.diagonal == pytest.approx(2 * diagonal)
    np.testing.assert_allclose(model.vertex_normals, normals, atol=1e-12)
    np.testing.assert_allclose(model.curvature.mean, curvature_before / 2, rtol=1e-3)
    _, distance = model.closest_points(np.zeros((1, 3)))
    assert distance[0] == pytest.approx(2 * before[0], rel=1e-6)  # the scene was rebuilt at the new size
    model.label = "ball"  # plain attributes stay assignable
    assert model.label == "ball"


def test_bad_assignment_is_refused_and_leaves_the_model_intact():
    model = primitives.sphere(R_MM, 1)
    before = model.vertices.copy()
    with pytest.raises(InvalidMeshError, match="out of range"):
        model.vertices = model.vertices[:5]
    np.testing.assert_array_equal(model.vertices, before)


def test_the_model_owns_its_arrays():
    s = primitives.sphere(R_MM, 1)
    vertices = s.vertices.copy()
    model = ObjectModel(vertices, s.triangles)
    vertices *= 2
    assert model.diagonal == pytest.approx(s.diagonal)


# --------------------------------------------------------------------------------- extreme coordinates
def test_far_from_the_origin_casts_rays_around_the_centre():
    s = primitives.sphere(R_MM, 2)
    near = ObjectModel(s.vertices, s.triangles, name="near")
    far = ObjectModel(s.vertices + 1e7, s.triangles, name="far")
    np.testing.assert_allclose(near.scene_origin, 0.0, atol=1e-9)  # the centre of the sphere
    np.testing.assert_array_equal(far.scene_origin, far.center)
    queries = np.array([[60.0, 0.0, 0.0], [0.0, -70.0, 10.0], [5.0, 5.0, 5.0]])
    (near_points, near_d), (far_points, far_d) = near.closest_points(queries), far.closest_points(queries + 1e7)
    np.testing.assert_allclose(far_points - 1e7, near_points, atol=1e-5)  # float32 at 1e7 would be 1 mm off
    np.testing.assert_allclose(far_d, near_d, atol=1e-5)
    near_view, far_view = render_views(near, 2, 24, 24)[0], render_views(far, 2, 24, 24)[0]
    np.testing.assert_array_equal(far_view.mask, near_view.mask)
    np.testing.assert_allclose(far_view.depth, near_view.depth, atol=1e-3)


@pytest.mark.parametrize("radius", [1e160, 1e-160])
def test_sphere_of_extreme_size_loads_scaled(tmp_path, radius):
    s = primitives.sphere(1.0, 2)
    model = load_object(write_off(tmp_path / "s.off", s.vertices * radius, s.triangles))
    assert model.size == pytest.approx(150.0)
    assert model.n_triangles == s.n_triangles
    expected, _ = normalize(s.vertices, triangles=s.triangles)
    np.testing.assert_allclose(model.vertices, expected, atol=1e-9)


def test_normalize_handles_opposite_extremes():
    v = np.array([[-1e308, 0, 0], [1e308, 0, 0], [0, 1e308, 0]])
    out, transform = normalize(v)
    assert np.isfinite(out).all() and np.isfinite(transform).all()
    # Three points, no triangles: centred on their mean, the furthest 75 mm from it.
    np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-9)
    assert 2 * np.linalg.norm(out, axis=1).max() == pytest.approx(150.0)
    out, _ = normalize(v, centering="bbox")
    assert np.linalg.norm(out.max(axis=0) - out.min(axis=0)) == pytest.approx(150.0)


def test_object_model_refuses_coordinates_that_overflow():
    s = primitives.sphere(1.0, 1)
    with pytest.raises(InvalidMeshError, match="size_mm"):
        ObjectModel(s.vertices * 1e160, s.triangles)


def test_unknown_methods_raise_project_errors_that_are_value_errors():
    model = primitives.sphere(R_MM, 1)
    for call in (
        lambda: model.compute_curvature("bogus"),
        lambda: curvature.vertex_normals(model.vertices, model.triangles, "bogus"),
    ):
        with pytest.raises(InvalidArgumentError) as info:
            call()
        assert isinstance(info.value, ValueError) and isinstance(info.value, VisuotactileError)


def test_bad_seeds_counts_and_channels_raise_project_errors():
    from perception.channels import compute_channels
    from perception.render import render_views, view_directions

    model = primitives.sphere(R_MM, 1)
    for seed in (-1, 1.5, "0", True):
        with pytest.raises(InvalidArgumentError, match="seed"):
            saliency(model, "mesh", seed=seed)
    with pytest.raises(InvalidArgumentError, match="n_views"):
        saliency(model, n_views=2.5)
    with pytest.raises(InvalidArgumentError, match="unknown saliency method"):
        saliency(model, "bogus")
    for call in (
        lambda: render_views(model, width=0),
        lambda: render_views(model, n_views=2.5),
        lambda: render_views(model, directions=[[0.0, 0.0, 0.0]]),
        lambda: view_directions(0),
        lambda: compute_channels(*[np.zeros((1, 8, 8))] * 2, np.zeros((1, 8, 8, 3)), np.ones((1, 8, 8), bool), 1.0, ("bogus",)),
    ):
        with pytest.raises(InvalidArgumentError):
            call()


def test_a_moebius_strip_cannot_be_oriented_and_is_left_as_it_is(caplog):
    from perception.orientation import orient_outward

    n = 24  # quads around the strip; the last one joins the first with the two rows swapped
    angle = 2 * np.pi * np.arange(n) / n
    centre = np.stack([40 * np.cos(angle), 40 * np.sin(angle), np.zeros(n)], 1)
    radial = np.stack([np.cos(angle), np.sin(angle), np.zeros(n)], 1)
    across = np.cos(angle / 2)[:, None] * radial + np.sin(angle / 2)[:, None] * [0.0, 0.0, 1.0]
    vertices = np.vstack([centre - 10 * across, centre + 10 * across])  # rows 0..n-1 and n..2n-1
    quads = [(i, i + 1, n + i + 1, n + i) for i in range(n - 1)] + [(n - 1, n, 0, 2 * n - 1)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    with caplog.at_level(logging.WARNING, logger="perception.orientation"):
        out, report = orient_outward(vertices, triangles, "moebius")
    assert report.non_orientable == 1
    np.testing.assert_array_equal(out, triangles)
    assert warned(caplog, "non-orientable")
