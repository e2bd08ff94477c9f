"""Contours: exact sections against analytic shapes and trimesh, probe poses, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perception import primitives
from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import list_collection, load_object
from tactile.contours import (
    Plane,
    choose_chain,
    interpolate_normals,
    make_contour,
    plane_through,
    section,
    section_chains,
    signed_area,
)

R = 50.0


@pytest.fixture(scope="module")
def sphere():
    return primitives.sphere(R, 5)


@pytest.fixture(scope="module")
def coarse_sphere():
    return primitives.sphere(R, 4)


def perimeter(points: np.ndarray, closed: bool = True) -> float:
    ends = np.roll(points, -1, axis=0) if closed else points[1:]
    return float(np.linalg.norm(ends - points[: len(ends)], axis=1).sum())


# ------------------------------------------------------------------------------------- planes
def test_plane_through_normal_is_the_normalised_cross_product():
    plane = plane_through([1.0, 1.0, 1.0], [3.0, 1.0, 1.0], [1.0, 1.0, 5.0])
    np.testing.assert_allclose(plane.normal, [0.0, -1.0, 0.0])
    np.testing.assert_allclose(plane.point, [1.0, 1.0, 1.0])


@pytest.mark.parametrize(
    "p1, p2",
    [
        ([1.0, 0, 0], [2.0, 0, 0]),
        ([1.0, 0, 0], [-3.0, 0, 0]),
        ([1.0, 0, 0], [1.0, 1e-5, 0]),
        ([0.0, 0, 0], [0, 1, 0]),
    ],
)
def test_plane_through_rejects_collinear_and_coincident_points(p1, p2):
    with pytest.raises(ContourError):
        plane_through([0.0, 0.0, 0.0], p1, p2)


def test_plane_rejects_zero_and_nan_normals():
    with pytest.raises(ContourError):
        Plane(np.zeros(3), np.zeros(3))
    with pytest.raises(ContourError):
        Plane(np.zeros(3), [np.nan, 0, 1])
    with pytest.raises(ContourError):
        plane_through([0, 0, 0], [np.inf, 0, 0], [0, 1, 0])


# ------------------------------------------------------------------------------------ section
def test_great_circle_perimeter_is_2_pi_r(sphere):
    loops = section_chains(sphere, Plane([0, 0, 0], [0.3, -0.2, 0.9]))
    assert len(loops) == 1 and loops[0].closed
    assert perimeter(loops[0].points) == pytest.approx(2 * np.pi * R, rel=5e-3)
    # Every section point lies on the mesh surface and in the plane.
    assert np.abs(loops[0].points @ Plane([0, 0, 0], [0.3, -0.2, 0.9]).normal).max() < 1e-9


@settings(max_examples=25, deadline=None)
@given(
    normal=st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda n: np.linalg.norm(n) > 0.1),
    offset=st.floats(-0.9, 0.9),
)
def test_any_plane_cuts_a_sphere_in_one_closed_circle(coarse_sphere, normal, offset):
    n = np.asarray(normal) / np.linalg.norm(normal)
    chains = section_chains(coarse_sphere, Plane(offset * R * n, n))
    assert len(chains) == 1 and chains[0].closed
    expected = 2 * np.pi * R * np.sqrt(1 - offset**2)
    assert perimeter(chains[0].points) == pytest.approx(expected, rel=5e-3)
    assert len(np.unique(chains[0].points, axis=0)) == len(chains[0].points)


def test_plane_through_vertices_along_edges_gives_one_clean_loop(sphere):
    # x = 0 holds 128 vertices of this icosphere and runs along the edges joining some of them.
    on_plane = np.flatnonzero(sphere.vertices[:, 0] == 0.0)
    in_plane_edges = (sphere.vertices[sphere.edges, 0] == 0.0).all(axis=1).sum()
    assert len(on_plane) == 128 and in_plane_edges > 0
    chains = section_chains(sphere, Plane([0, 0, 0], [1, 0, 0]))
    assert len(chains) == 1 and chains[0].closed
    pts = chains[0].points
    assert len(np.unique(pts, axis=0)) == len(pts)
    # Every on-plane vertex appears exactly once, as itself.
    hits = (pts[:, None, :] == sphere.vertices[on_plane][None, :, :]).all(axis=2)
    np.testing.assert_array_equal(hits.sum(axis=0), 1)
    assert perimeter(pts) == pytest.approx(2 * np.pi * R, rel=5e-3)


def test_plane_along_a_cylinder_ring_row_gives_the_ring():
    cyl = primitives.cylinder(30.0, 100.0, n_around=64, n_along=32)
    z = np.linspace(-50.0, 50.0, 32)[10]
    chains = section_chains(cyl, Plane([0, 0, z], [0, 0, 1]))
    assert len(chains) == 1 and chains[0].closed
    assert len(chains[0].points) == 64 and len(np.unique(chains[0].points, axis=0)) == 64
    assert perimeter(chains[0].points) == pytest.approx(64 * 2 * 30.0 * np.sin(np.pi / 64), rel=1e-12)


def test_plane_on_a_coplanar_cap_gives_its_rim():
    cyl = primitives.cylinder(30.0, 100.0, n_around=64, n_along=8)
    chains = section_chains(cyl, Plane([0, 0, 50.0], [0, 0, 1]))
    assert len(chains) == 1 and chains[0].closed and len(chains[0].points) == 64
    np.testing.assert_allclose(np.hypot(*chains[0].points[:, :2].T), 30.0)


def test_axial_cut_of_a_cylinder_is_its_exact_rectangle():
    # x = 0 runs through two vertex columns of the side and the centres of the fan caps: a 60 x 100 rectangle.
    cyl = primitives.cylinder(30.0, 100.0, n_around=64, n_along=8)
    chains = section_chains(cyl, Plane([0, 0, 0], [1, 0, 0]))
    assert len(chains) == 1 and chains[0].closed
    assert perimeter(chains[0].points) == pytest.approx(2 * 100 + 4 * 30, rel=1e-12)
    assert abs(signed_area(chains[0].points, Plane([0, 0, 0], [1, 0, 0]))) == pytest.approx(6000.0, rel=1e-12)


def test_section_matches_trimesh_on_a_real_mesh(shrec07):
    trimesh = pytest.importorskip("trimesh")
    path, _ = list_collection(shrec07)[25]
    model = load_object(path)
    peer = trimesh.Trimesh(model.vertices, model.triangles, process=False)
    rng = np.random.default_rng(4)
    for _ in range(5):
        n = rng.normal(size=3)
        plane = Plane(model.center + rng.normal(scale=5.0, size=3), n)
        ours = sum(c.length_mm for c in section_chains(model, plane))
        path3d = peer.section(plane_origin=plane.point, plane_normal=plane.normal)
        theirs = 0.0 if path3d is None else float(path3d.length)
        assert ours == pytest.approx(theirs, rel=1e-6)


def test_section_returns_point_arrays(sphere):
    loops = section(sphere, Plane([0, 0, 10.0], [0, 0, 1]))
    assert len(loops) == 1 and loops[0].shape[1] == 3


# ----------------------------------------------------------------------------------- contours
def test_outer_loop_is_chosen_on_a_torus():
    torus = primitives.torus(50.0, 20.0, 64, 32)
    plane = Plane([0, 0, 0], [0, 0, 1])
    chains = section_chains(torus, plane)
    assert len(chains) == 2
    outer = choose_chain(chains, plane)
    assert np.hypot(*outer.points[:, :2].T).max() == pytest.approx(70.0)
    assert signed_area(outer.points, plane) == pytest.approx(np.pi * 70.0**2, rel=2e-3)
    contour = make_contour(torus, plane)
    np.testing.assert_allclose(np.hypot(*contour.positions[:, :2].T), 70.0, rtol=2e-3)


def test_probes_are_equally_spaced_and_posed_on_a_sphere(sphere):
    plane = plane_through([0, 0, 0], [1, 2, 0.5], [-1, 0.3, 2])
    contour = make_contour(sphere, plane, n_probes=25)
    assert contour.closed and contour.positions.shape == (25, 3)
    # Equal arc length: consecutive chords of a circle are equal.
    chords = np.linalg.norm(np.diff(np.vstack([contour.positions, contour.positions[:1]]), axis=0), axis=1)
    np.testing.assert_allclose(chords, 2 * R * np.sin(np.pi / 25), rtol=2e-3)
    exact, _, _ = primitives.analytic_sphere(contour.positions, R)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", contour.normals, exact), -1, 1)))
    assert angle.max() < 0.05  # interpolated vertex normals, far closer than the facets (~0.9 deg apart)
    np.testing.assert_allclose(np.linalg.norm(contour.tangents, axis=1), 1.0)
    assert np.abs(np.einsum("ij,ij->i", contour.tangents, contour.normals)).max() < 1e-12
    np.testing.assert_allclose(contour.binormals, np.cross(contour.normals, contour.tangents))
    # Counter-clockwise about the plane normal.
    assert (np.cross(contour.positions, contour.tangents) @ plane.normal > 0).all()


def test_interpolated_normal_at_a_vertex_is_the_vertex_normal(sphere):
    tri = 123
    v = sphere.triangles[tri]
    normals = interpolate_normals(sphere, sphere.vertices[v], np.full(3, tri))
    np.testing.assert_allclose(normals, sphere.vertex_normals[v], atol=1e-12)


def test_start_point_and_determinism(sphere):
    plane = Plane([0, 0, 0], [0, 0, 1])
    a, b = make_contour(sphere, plane), make_contour(sphere, plane)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.normals, b.normals)
    start = make_contour(sphere, plane, start=[0, -R, 0])
    assert np.linalg.norm(start.positions[0] - [0, -R, 0]) < 2.0


def test_open_mesh_gives_the_longest_chain_end_to_end():
    flat = primitives.plane(100.0, 21)
    contour = make_contour(flat, Plane([0, 0, 0], [1, 0, 0]), n_probes=11)
    assert not contour.closed
    np.testing.assert_allclose(
        contour.positions[:, 1], np.linspace(-50, 50, 11) * np.sign(contour.positions[-1, 1])
    )
    np.testing.assert_allclose(contour.normals, np.tile([0, 0, 1.0], (11, 1)))


def test_soup_contours_are_finite(psb_open):
    model = load_object(min(psb_open.glob("*.obj")))
    rng = np.random.default_rng(0)
    for _ in range(5):
        i, j = rng.choice(model.n_vertices, 2, replace=False)
        contour = make_contour(model, plane_through(model.center, model.vertices[i], model.vertices[j]))
        for array in (contour.positions, contour.normals, contour.tangents):
            assert np.isfinite(array).all()
        _, distance = model.closest_points(contour.positions)
        assert distance.max() < 1e-3


def test_contours_on_real_meshes_lie_on_the_surface(shrec07):
    model = load_object(list_collection(shrec07)[0][0])
    rng = np.random.default_rng(1)
    for _ in range(5):
        i, j = rng.choice(model.n_vertices, 2, replace=False)
        contour = make_contour(model, plane_through(model.center, model.vertices[i], model.vertices[j]))
        assert contour.closed and np.isfinite(contour.normals).all()
        _, distance = model.closest_points(contour.positions)
        assert distance.max() < 1e-3


# ---------------------------------------------------------------------------------- bad input
def test_plane_missing_the_object_names_it(sphere):
    with pytest.raises(ContourError, match=sphere.name):
        make_contour(sphere, Plane([0, 0, 2 * R], [0, 0, 1]))


def test_tangent_plane_touching_one_vertex_is_a_miss(sphere):
    top = sphere.vertices[np.argmax(sphere.vertices[:, 2])]
    assert section(sphere, Plane(top, [0, 0, 1])) == []


@pytest.mark.parametrize("n", [0, 1, -3, 2.5])
def test_too_few_probes(sphere, n):
    with pytest.raises(InvalidArgumentError):
        make_contour(sphere, Plane([0, 0, 0], [0, 0, 1]), n_probes=n)


def test_loop_walk_and_general_walk_find_the_same_loops():
    """Two independent chainers (the degree-2 fast path and the general walk, forced by an extra open chain)
    give the same cycles: a triangle and a square, edges shuffled."""
    from tactile.contours import _walk

    loops = [[0, 1, 2], [3, 4, 5, 6]]
    edges = [(c[i], c[(i + 1) % len(c)]) for c in loops for i in range(len(c))]
    order = np.random.default_rng(0).permutation(len(edges))
    closed_only = np.array(edges)[order]
    with_chain = np.concatenate([closed_only, [[7, 8], [8, 9]]])  # nodes 7 and 9 have degree 1

    def cycles(walks):
        out = set()
        for nodes, path, closed in walks:
            if closed:
                k = nodes.index(min(nodes))
                ring = nodes[k:] + nodes[:k]
                out.add(tuple(min(ring, [ring[0]] + ring[1:][::-1])))  # one direction per cycle
        return out

    expected = {(0, 1, 2), (3, 4, 5, 6)}
    fast = _walk(closed_only, 7)
    general = _walk(with_chain, 10)
    assert cycles(fast) == expected == cycles(general)
    assert [w for w in general if not w[2]] in ([([7, 8, 9], [7, 8], False)], [([9, 8, 7], [8, 7], False)])
    for nodes, path, _ in fast:  # each loop's edges join its consecutive nodes
        for k, e in enumerate(path):
            assert set(closed_only[e]) == {nodes[k], nodes[(k + 1) % len(nodes)]}
