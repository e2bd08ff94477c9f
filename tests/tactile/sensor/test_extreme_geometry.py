"""Extreme geometry through contours and the tactile sensor.

Every mesh is built here from a known shape; every case ends in a project exception or finite output whose
stated invariant is checked against an answer computed independently of the code under test (convex
polygons for cube sections, face normals and wedge imprints at edges and corners, similar triangles for a
tetrahedron, the analytic cap of a small sphere). Already covered elsewhere, not repeated: planes through
sphere vertices and along its edges and the coplanar cap of a cylinder (tests/tactile/test_contours.py), the
flat plate and the inward-wound sphere (tests/tactile/test_robustness.py), the bowtie, the self-intersecting
merged spheres and the tetrahedron's curvature (tests/perception/test_robustness.py).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from perception import primitives
from perception.errors import ContourError
from perception.geometry import ObjectModel, load_object
from perception.saliency import saliency
from tactile.contours import Plane, interpolate_normals, make_contour, section_chains
from tactile.explore import explore
from tactile.sampling import explore_object
from tactile.sensor import FSRSensor
from tests.perception.test_robustness import write_off

H = 50.0  # half side of the test cubes, mm
SMALL = FSRSensor(rows=8, cols=8)


# ------------------------------------------------------------------------------------------ shapes
def grid_cube(half: float = H, n: int = 2, flip: bool = False, center=(0.0, 0.0, 0.0)):
    """Cube [-half, half]^3 + center, each face an n x n grid of squares cut along one diagonal (the other
    with ``flip``), vertices shared, wound outward. Returns (vertices, triangles)."""
    s = np.linspace(-1.0, 1.0, n + 1)
    points, faces = [], []
    for axis, sign in itertools.product(range(3), (-1.0, 1.0)):
        u, v = [a for a in range(3) if a != axis]
        grid = np.zeros((n + 1, n + 1, 3))
        grid[..., axis] = sign
        grid[..., u], grid[..., v] = np.meshgrid(s, s, indexing="ij")
        idx = sum(len(p) for p in points) + np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
        points.append(grid.reshape(-1, 3))
        a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        cut = [(a, b, d), (b, c, d)] if flip else [(a, b, c), (a, c, d)]
        faces += [np.stack(t, -1).reshape(-1, 3) for t in cut]
    unit, tri = np.concatenate(points), np.concatenate(faces)
    cross = np.cross(unit[tri[:, 1]] - unit[tri[:, 0]], unit[tri[:, 2]] - unit[tri[:, 0]])
    inward = np.einsum("ij,ij->i", cross, unit[tri].mean(axis=1)) < 0
    tri[inward] = tri[inward][:, ::-1]
    _, first, inverse = np.unique(np.round(unit * n).astype(np.int64), axis=0, return_index=True, return_inverse=True)
    return unit[first] * half + np.asarray(center), inverse.ravel()[tri]


def cube_model(half: float = H, n: int = 2, flip: bool = False, name: str = "cube") -> ObjectModel:
    return ObjectModel(*grid_cube(half, n, flip), name=name)


def convex_section(corners: np.ndarray, plane: Plane) -> tuple[float, bool]:
    """Length of the section of the convex hull of ``corners`` by ``plane``, computed from the hull's edges
    alone (no triangles): its perimeter (closed) or, where the plane only touches an edge, that edge's length
    (open). (0, False) where it misses or touches a single point."""
    hull_edges = [(i, j) for i, j in itertools.combinations(range(len(corners)), 2)
                  if np.count_nonzero(corners[i] != corners[j]) == 1]  # axis-aligned box: the 12 edges
    d = (corners - plane.point) @ plane.normal
    d[np.abs(d) < 1e-9] = 0.0
    pts = [corners[i] for i in range(len(corners)) if d[i] == 0]
    pts += [corners[i] + d[i] / (d[i] - d[j]) * (corners[j] - corners[i]) for i, j in hull_edges if d[i] * d[j] < 0]
    pts = np.unique(np.round(np.array(pts).reshape(-1, 3), 9), axis=0)
    if len(pts) < 2:
        return 0.0, False
    u, v = plane.basis()
    flat = np.stack([(pts - plane.point) @ u, (pts - plane.point) @ v], axis=1)
    if np.linalg.matrix_rank(flat - flat[0], tol=1e-9) < 2:  # collinear: the plane touches along an edge
        return float(max(np.linalg.norm(a - b) for a, b in itertools.combinations(flat, 2))), False
    ring = flat[ConvexHull(flat).vertices]
    return float(np.linalg.norm(ring - np.roll(ring, -1, axis=0), axis=1).sum()), True


def assert_on_surface(model: ObjectModel, points: np.ndarray, tol: float = 1e-4) -> None:
    _, distance = model.closest_points(points)
    assert distance.max() < tol


def assert_sequence_sane(sequence, sensor: FSRSensor) -> None:
    """The documented invariants of a tactile sequence."""
    for array in (sequence.frames, sequence.normals, sequence.positions, sequence.tangents, sequence.pad_sides_mm):
        assert np.isfinite(array).all()
    assert sequence.frames.min() >= 0.0 and sequence.frames.max() <= sensor.range_mm
    assert ((sequence.pad_sides_mm >= sensor.min_side_mm) & (sequence.pad_sides_mm <= sensor.side_mm)).all()
    np.testing.assert_allclose(np.linalg.norm(sequence.normals, axis=1), 1.0, atol=1e-9)


# ------------------------------------------------------------------- planes through vertices and edges
def lattice_planes():
    """Every plane n . x = c with n in {-1, 0, 1}^3 (up to sign) and c a multiple of H / 2 that meets the
    cube: through its vertices, along its edges and face diagonals, containing faces, touching at a vertex."""
    for normal in itertools.product((-1, 0, 1), repeat=3):
        if normal <= (0, 0, 0):
            continue  # zero, or the negative of one already listed
        reach = int(np.abs(normal).sum())
        for j in range(-2 * reach, 2 * reach + 1):
            c = j * H / 2
            yield Plane(c * np.asarray(normal, float) / np.dot(normal, normal), normal)


LATTICE = list(lattice_planes())
CORNERS = np.array(list(itertools.product((-H, H), repeat=3)))


@pytest.mark.parametrize("flip", [False, True], ids=["diagonal-a", "diagonal-b"])
def test_cube_sections_through_vertices_edges_and_faces_are_the_convex_polygon(flip):
    model = cube_model(flip=flip)
    closed_cuts = touching = 0
    for plane in LATTICE:
        expected, closed = convex_section(CORNERS, plane)
        chains = section_chains(model, plane)
        if expected == 0:
            assert chains == [], plane.to_dict()  # misses, or touches one corner only
            with pytest.raises(ContourError):
                make_contour(model, plane, 4)
            continue
        assert len(chains) == 1 and chains[0].closed == closed, plane.to_dict()
        assert chains[0].length_mm == pytest.approx(expected, rel=1e-12), plane.to_dict()
        contour = make_contour(model, plane, 12)
        assert np.abs((contour.positions - plane.point) @ plane.normal).max() < 1e-9
        assert np.abs(contour.positions).max() == pytest.approx(H)  # every probe on a face of the cube
        assert (np.abs(contour.positions) <= H + 1e-9).all()
        np.testing.assert_allclose(np.linalg.norm(contour.normals, axis=1), 1.0, atol=1e-12)
        closed_cuts += closed
        touching += not closed
    assert (len(LATTICE), closed_cuts, touching) == (121, 101, 12)  # the case counts of the README table


def test_plane_containing_a_face_follows_its_rim_with_edge_and_corner_normals():
    model = cube_model(n=2)
    contour = make_contour(model, Plane([0, 0, H], [0, 0, 1]), 8, start=[H, H, H])
    assert contour.closed and contour.length_mm == pytest.approx(8 * H)
    # Probes every H along the rim: corners and edge midpoints, all vertices of the grid.
    expected = np.array([[1, 1, 1], [0, 1, 1], [-1, 1, 1], [-1, 0, 1], [-1, -1, 1], [0, -1, 1], [1, -1, 1], [1, 0, 1]])
    np.testing.assert_allclose(contour.positions, H * expected, atol=1e-9)
    # Angle-weighted vertex normals: a corner sees three faces at 90 degrees, an edge point two at 180.
    np.testing.assert_allclose(contour.normals, expected / np.linalg.norm(expected, axis=1, keepdims=True), atol=1e-12)


# ------------------------------------------------------------------------------- edges and corners
def test_probes_on_sharp_edges_read_the_wedge_and_flat_faces_read_zero():
    model = cube_model(n=4)
    sensor = FSRSensor()
    contour = make_contour(model, Plane([0, 0, 0], [0, 0, 1]), 16, start=[H, H, 0])
    sequence = explore(model, contour, sensor)
    assert_sequence_sane(sequence, sensor)
    corner = np.abs(np.abs(contour.positions[:, 0]) - np.abs(contour.positions[:, 1])) < 1e-9
    assert corner.sum() == 4  # the four vertical edges
    # On an edge the normal bisects the two faces; elsewhere it is the face's own normal.
    expected = np.where(np.abs(contour.positions) >= H - 1e-9, np.sign(contour.positions), 0.0)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(contour.normals, expected, atol=1e-12)
    # Pad across a 90-degree edge, normal on the bisector: the faces fall away at 45 degrees, gap = |x|.
    x = sensor.taxel_coordinates()[..., 0]
    np.testing.assert_allclose(sequence.frames[corner], np.broadcast_to(np.abs(x), (4, 32, 32)), atol=1e-4)
    assert np.abs(sequence.frames[~corner]).max() < 1e-4
    np.testing.assert_array_equal(sequence.pad_sides_mm, sensor.side_mm)  # convex: never shrinks


def test_a_probe_on_a_corner_reads_the_trihedral_imprint():
    model = cube_model(n=2)
    contour = make_contour(model, Plane([0, 0, 0], [1, -1, 0]), 10, start=[H, H, H])
    np.testing.assert_array_equal(contour.positions[0], [H, H, H])
    normal = np.ones(3) / np.sqrt(3)
    np.testing.assert_allclose(contour.normals[0], normal, atol=1e-12)
    sensor = FSRSensor(range_mm=30.0)
    tangent = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    frames, sides = sensor.press(model, [[H, H, H]], [normal], [tangent])
    # The pad point p (in the plane through the corner) sees face i at depth (p . e_i) / (n . e_i): the
    # deepest of the three is where the ray enters the solid corner.
    xy = sensor.taxel_coordinates()
    p = xy[..., :1] * tangent + xy[..., 1:] * np.cross(normal, tangent)
    np.testing.assert_allclose(frames[0], np.sqrt(3) * p.max(axis=-1), atol=1e-4)
    assert sides[0] == sensor.side_mm


# --------------------------------------------------------------------------- degenerate triangles
def t_junction_sliver(half: float = H):
    """An 8-vertex cube whose top-face triangle next to an edge (a, b) along x is split at the edge's midpoint
    m, the crack closed by the zero-area triangle (a, b, m): watertight, one face of zero area."""
    v, t = grid_cube(half, n=1)
    top = np.flatnonzero((v[t][:, :, 2] == half).all(axis=1))
    for i, k in itertools.product(top, range(3)):
        a, b, c = t[i][k], t[i][(k + 1) % 3], t[i][(k + 2) % 3]
        if v[a][2] == v[b][2] == half and v[a][1] == v[b][1]:  # the edge along x, not the diagonal
            break
    m = len(v)
    triangles = np.vstack([np.delete(t, i, axis=0), [[a, m, c], [m, b, c], [a, b, m]]])
    return np.vstack([v, (v[a] + v[b]) / 2]), triangles


CUTS = [Plane([0, 0, 0], n) for n in ([1, 0, 0.05], [0.05, 1, 0.02], [0.3, 1, 0.2], [0, 1, 0])]


def test_zero_area_sliver_closing_a_t_junction_keeps_the_loop_closed():
    model = ObjectModel(*t_junction_sliver(), name="sliver")
    assert model.is_watertight and (model.triangle_areas == 0).sum() == 1
    for plane in CUTS:
        (chain,) = section_chains(model, plane)
        assert chain.closed and chain.length_mm == pytest.approx(convex_section(CORNERS, plane)[0], rel=1e-12)
        sequence = explore(model, make_contour(model, plane, 12), SMALL)
        assert_sequence_sane(sequence, SMALL)
        assert_on_surface(model, sequence.positions)


def test_t_junction_crack_after_repair_still_gives_a_closed_contour(tmp_path):
    model = load_object(write_off(tmp_path / "sliver.off", *t_junction_sliver()), size_mm=None)
    assert not model.is_watertight  # the sliver is gone: a crack along the edge
    plane = CUTS[0]  # crosses the split edge
    assert sum(c.length_mm for c in section_chains(model, plane)) == pytest.approx(
        convex_section(CORNERS, plane)[0], rel=1e-12
    )
    contour = make_contour(model, plane, 12)
    assert contour.closed
    assert np.linalg.norm(np.diff(contour.positions, axis=0), axis=1).min() > 1.0


def needle_cube(gap_mm: float):
    """An 8-vertex cube whose top face is a fan around a vertex ``gap_mm`` from one of its edges: the
    triangle on that edge is a needle (height gap_mm, base 2 H)."""
    v, t = grid_cube(H, n=1)
    keep = ~(v[t][:, :, 2] == H).all(axis=1)
    ring = [i for i in np.flatnonzero(v[:, 2] == H)]
    ring.sort(key=lambda i: np.arctan2(v[i, 1], v[i, 0]))  # counter-clockwise seen from above
    m = len(v)
    fan = [[ring[k], ring[(k + 1) % 4], m] for k in range(4)]
    return np.vstack([v, [0.0, -H + gap_mm, H]]), np.vstack([t[keep], fan])


@pytest.mark.parametrize("gap_mm", [1e-6, 1e-12])
def test_needle_triangles_give_finite_unit_normals_inside_the_blend(tmp_path, gap_mm):
    raw = ObjectModel(*needle_cube(gap_mm), name="needle")
    assert raw.is_watertight
    needle = int(np.argmin(raw.triangle_areas))
    assert raw.triangle_areas[needle] == pytest.approx(H * gap_mm, rel=1e-3)
    for model in (raw, load_object(write_off(tmp_path / "needle.off", *needle_cube(gap_mm)), size_mm=None)):
        assert model.n_triangles == 12 + 2  # the needle has area: repair keeps it
        index = int(np.argmin(model.triangle_areas))
        corners = model.vertices[model.triangles[index]]
        weights = np.random.default_rng(0).dirichlet(np.ones(3), size=50)
        normals = interpolate_normals(model, weights @ corners, np.full(50, index))
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
        # Its three vertex normals point up and towards -y: so does any blend of them.
        assert (normals[:, 2] > 0).all() and (normals[:, 1] <= 1e-12).all() and np.isfinite(normals).all()
        plane = Plane([0.3, 0, 0], [1, 0, 0.02])  # crosses the needle
        (chain,) = section_chains(model, plane)
        assert chain.closed
        assert chain.length_mm == pytest.approx(convex_section(CORNERS, plane)[0], abs=4 * gap_mm + 1e-9)
        sequence = explore(model, make_contour(model, plane, 12, start=[0.3, -H, H]), SMALL)
        assert_sequence_sane(sequence, SMALL)


# ---------------------------------------------------------------------------- duplicated vertices
def test_duplicated_vertices_are_merged_on_load_and_a_raw_soup_gives_its_longest_piece(tmp_path):
    v, t = grid_cube(H, n=2)
    soup_v, soup_t = v[t].reshape(-1, 3), np.arange(3 * len(t)).reshape(-1, 3)  # no vertex shared
    plane = CUTS[2]
    expected, _ = convex_section(CORNERS, plane)
    loaded = load_object(write_off(tmp_path / "soup.off", soup_v, soup_t), size_mm=None)
    assert loaded.n_vertices == len(v) and loaded.is_watertight
    (chain,) = section_chains(loaded, plane)
    assert chain.closed and chain.length_mm == pytest.approx(expected, rel=1e-12)
    raw = ObjectModel(soup_v, soup_t, name="soup")
    chains = section_chains(raw, plane)
    assert all(not c.closed and len(c.points) == 2 for c in chains)
    assert sum(c.length_mm for c in chains) == pytest.approx(expected, rel=1e-12)
    # By hand: the longest piece of the plane inside one triangle.
    d = (soup_v - plane.point) @ plane.normal
    pieces = []
    for tri in soup_t:
        ends = [soup_v[i] + d[i] / (d[i] - d[j]) * (soup_v[j] - soup_v[i])
                for i, j in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])) if d[i] * d[j] < 0]
        if len(ends) == 2:
            pieces.append(np.linalg.norm(ends[1] - ends[0]))
    contour = make_contour(raw, plane, 5)
    assert not contour.closed and contour.length_mm == pytest.approx(max(pieces), rel=1e-12)
    assert_sequence_sane(explore(raw, contour, SMALL), SMALL)


# ------------------------------------------------------------------------ non-manifold, open, parts
def test_two_cubes_sharing_an_edge_give_two_loops_through_the_shared_point(tmp_path):
    va, ta = grid_cube(H, n=2)
    vb, tb = grid_cube(H, n=2, center=(2 * H, 2 * H, 0))
    model = load_object(write_off(tmp_path / "edge.off", np.vstack([va, vb]), np.vstack([ta, tb + len(va)])), size_mm=None)
    assert model.n_vertices == 2 * len(va) - 3  # the shared edge's three vertices merged
    edges = np.sort(model._directed_edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() == 4 and not model.is_watertight  # non-manifold: four faces on the shared edge
    plane = Plane([0, 0, 0.3], [0, 0.1, 1])  # crosses the shared edge
    chains = section_chains(model, plane)
    one, _ = convex_section(CORNERS, plane)
    assert sorted(c.closed for c in chains) == [True, True]
    np.testing.assert_allclose([c.length_mm for c in chains], [one, one], rtol=1e-12)
    shared = np.array([H, H, 0.3 - 0.1 * H])
    for chain in chains:
        assert np.linalg.norm(chain.points - shared, axis=1).min() < 1e-9
    contour = make_contour(model, plane, 12, start=shared)
    np.testing.assert_allclose(contour.positions[0], shared, atol=1e-9)
    sequence = explore(model, contour, SMALL)
    assert_sequence_sane(sequence, SMALL)
    assert_on_surface(model, sequence.positions)


def three_fins(length: float = 40.0, height: float = 30.0):
    """Three rectangles (``length`` x 2 ``height``) sharing the edge x = y = 0: a non-manifold open surface.
    Returns the model and the fins' unit directions."""
    directions = np.array([[1.0, 0, 0], [0, 1.0, 0], [-np.sqrt(0.5), -np.sqrt(0.5), 0]])
    vertices = [[0, 0, -height], [0, 0, height]]
    triangles = []
    for d in directions:
        k = len(vertices)
        vertices += [length * d + [0, 0, -height], length * d + [0, 0, height]]
        triangles += [[0, k, k + 1], [0, k + 1, 1]]
    return ObjectModel(np.array(vertices), np.array(triangles), name="fins"), directions


FIN_PLANE = Plane([0, 0, 1.0], [0, 0.05, 1])


def fin_lengths(directions, length: float = 40.0) -> list[float]:
    """Each fin is cut from the shared edge to its outer edge, the plane tilted by 0.05 in y."""
    return [length * float(np.linalg.norm([d[0], d[1], -0.05 * d[1]])) for d in directions]


def test_three_fins_on_one_edge_give_open_chains_of_the_right_total_length():
    model, directions = three_fins()
    chains = section_chains(model, FIN_PLANE)
    assert not any(c.closed for c in chains)
    assert sum(c.length_mm for c in chains) == pytest.approx(sum(fin_lengths(directions)), rel=1e-12)
    contour = make_contour(model, FIN_PLANE, 9)
    assert contour.length_mm == pytest.approx(max(c.length_mm for c in chains), rel=1e-12)
    assert_sequence_sane(explore(model, contour, SMALL), SMALL)


def test_three_fins_contour_runs_through_the_branch():
    model, directions = three_fins()
    contour = make_contour(model, FIN_PLANE, 9)
    assert contour.length_mm >= sum(sorted(fin_lengths(directions))[:2]) - 1e-9  # two fins joined


def test_open_box_cuts_a_closed_ring_and_an_open_u():
    v, t = grid_cube(H, n=2)
    model = ObjectModel(v, t[~(v[t][:, :, 2] == H).all(axis=1)], name="open box")
    assert not model.is_watertight
    ring = make_contour(model, Plane([0, 0, 0], [0, 0.1, 1]), 12)
    assert ring.closed and ring.length_mm == pytest.approx(convex_section(CORNERS, Plane([0, 0, 0], [0, 0.1, 1]))[0])
    u = make_contour(model, Plane([0.3, 0, 0], [1, 0, 0]), 13)
    assert not u.closed and u.length_mm == pytest.approx(6 * H)  # two walls and the floor
    np.testing.assert_allclose(u.positions[[0, -1], 2], H)  # it ends on the open rim
    for contour in (ring, u):
        sequence = explore(model, contour, SMALL)
        assert_sequence_sane(sequence, SMALL)
        assert_on_surface(model, sequence.positions)


def test_closed_self_intersecting_mesh_picks_the_outer_loop():
    va, ta = grid_cube(30.0, n=4)
    vb, tb = grid_cube(40.0, n=4, center=(40.0, 13.0, 7.0))  # overlaps the first, no face shared
    model = ObjectModel(np.vstack([va, vb]), np.vstack([ta, tb + len(va)]), name="overlap")
    assert model.is_watertight and model.to_open3d().is_self_intersecting()
    plane = Plane([0, 0, 0], [0, 0, 1])
    lengths = sorted(c.length_mm for c in section_chains(model, plane))
    np.testing.assert_allclose(lengths, [8 * 30.0, 8 * 40.0], rtol=1e-12)
    contour = make_contour(model, plane, 16)
    # The loop of larger area is the second cube's square: every probe on its boundary.
    local = np.abs(contour.positions[:, :2] - [40.0, 13.0])
    np.testing.assert_allclose(local.max(axis=1), 40.0, atol=1e-9)
    sequence = explore(model, contour, SMALL)  # some probes lie inside the other cube: still finite
    assert_sequence_sane(sequence, SMALL)
    assert_on_surface(model, sequence.positions)


def test_disconnected_parts_touch_the_larger_part_and_explore_finitely():
    va, ta = grid_cube(40.0, n=2)
    vb, tb = grid_cube(10.0, n=2, center=(100.0, 0.0, 0.0))
    model = ObjectModel(np.vstack([va, vb]), np.vstack([ta, tb + len(va)]), name="two parts")
    plane = Plane([50.0, 0, 0], [0, 0, 1])
    assert sorted(c.length_mm for c in section_chains(model, plane)) == pytest.approx([80.0, 320.0])
    contour = make_contour(model, plane, 8)
    np.testing.assert_allclose(np.abs(contour.positions[:, :2]).max(axis=1), 40.0)  # the large cube
    for sequence in explore_object(model, "blind", 4, sensor=SMALL, probes=10, seed=3):
        assert_sequence_sane(sequence, SMALL)
        assert_on_surface(model, sequence.positions)


# ----------------------------------------------------------------------------------- pad sizes
def test_pad_larger_than_the_object_reads_the_cap_and_the_range():
    radius = 3.0  # a 6 mm ball under a 20 mm pad
    model = primitives.sphere(radius, 4)
    sensor = FSRSensor()
    contour = make_contour(model, Plane([0, 0, 0], [0.2, 0.3, 1]), 6)
    sequence = explore(model, contour, sensor)
    assert_sequence_sane(sequence, sensor)
    np.testing.assert_array_equal(sequence.pad_sides_mm, sensor.side_mm)
    rho = np.linalg.norm(sensor.taxel_coordinates(), axis=-1)
    over, beside = rho < radius - 0.1, rho > radius + 0.01
    cap = radius - np.sqrt(radius**2 - rho[over] ** 2)
    assert np.abs(sequence.frames[:, over] - cap).max() < 0.02  # tessellation: 0.1 mm edges
    assert (sequence.frames[:, beside] == sensor.range_mm).all()  # rays beside the ball miss


SLOT = {"width": 60.0, "depth": 60.0, "height": 40.0, "slot_width": 2.0, "slot_depth": 25.0}


def slotted_block() -> ObjectModel:
    """A 60 x 60 x 40 mm block with a 2 mm wide, 25 mm deep slot across its top (along y), refined to 5 mm
    edges so that flat faces have vertices with their own normal."""
    import manifold3d as mf

    w, d, h, sw, sd = SLOT.values()
    block = mf.Manifold.cube((w, d, h), True) - mf.Manifold.cube((sw, d + 10, sd + 1), True).translate(
        (0, 0, h / 2 - sd / 2 + 0.5)
    )
    mesh = block.refine_to_length(5.0).to_mesh()
    return ObjectModel(np.asarray(mesh.vert_properties)[:, :3].astype(np.float64), np.asarray(mesh.tri_verts),
                       name="slotted block")


def test_deep_narrow_slot_drives_the_pad_to_its_minimum_and_the_sequence_says_so():
    model = slotted_block()
    assert model.is_watertight
    w, _, h, sw, sd = SLOT.values()
    plane = Plane([0, 0, 0], [0, 1, 0])
    contour = make_contour(model, plane, 50)
    assert contour.closed and contour.length_mm == pytest.approx(2 * w + 2 * h + 2 * sd)  # the U-notched rectangle
    sensor = FSRSensor()  # sides 20 -> 5 mm: even the smallest pad is wider than the 2 mm slot
    sequence = explore(model, contour, sensor)
    assert_sequence_sane(sequence, sensor)
    x, z = contour.positions[:, 0], contour.positions[:, 2]
    in_slot = (np.abs(x) <= sw / 2 + 1e-9) & (z > h / 2 - sd - 1e-9) & (z < h / 2 - 1e-9)
    assert in_slot.sum() >= 8
    np.testing.assert_array_equal(sequence.pad_sides_mm[in_slot], sensor.min_side_mm)
    # Still penetrating at the recorded minimum: the floor was reached, not a fit.
    bottom = in_slot & (np.abs(z - (h / 2 - sd)) < 1e-9)
    gaps = sensor.measure_gaps(model, contour.positions[bottom], contour.normals[bottom],
                               contour.tangents[bottom], sensor.min_side_mm)
    assert (gaps.min(axis=(1, 2)) < -sensor.penetration_eps_mm).all()
    floor = np.abs(z + h / 2) < 1e-9
    assert floor.sum() >= 8
    np.testing.assert_array_equal(sequence.pad_sides_mm[floor & (np.abs(x) < w / 2 - 5)], sensor.side_mm)


# ----------------------------------------------------------------------------------- tetrahedron
def test_one_tetrahedron_goes_through_contours_touch_and_attention(tmp_path):
    corners = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    model = load_object(write_off(tmp_path / "tetra.off", corners, faces[:, ::-1]))  # inward: turned outward
    assert model.n_vertices == 4 and model.is_watertight and model.diagonal == pytest.approx(150.0)
    assert (np.einsum("ij,ij->i", model.triangle_normals, model.vertices[model.triangles].mean(axis=1)) > 0).all()
    edge = np.linalg.norm(model.vertices[0] - model.vertices[1])
    # Parallel to a face through the centroid: the similar triangle at 3/4 scale.
    apex = model.vertices[0]
    parallel = make_contour(model, Plane([0, 0, 0], apex), 6)
    assert parallel.closed and parallel.length_mm == pytest.approx(3 * 0.75 * edge, rel=1e-12)
    # Through an edge and the centroid: the edge and the two medians to the opposite edge's midpoint.
    through = make_contour(model, Plane([0, 0, 0], np.cross(model.vertices[0], model.vertices[1])), 6)
    assert through.length_mm == pytest.approx(edge * (1 + np.sqrt(3)), rel=1e-12)
    for method in ("multiview", "mesh", "iss"):
        scores = saliency(model, method, n_views=4, size_px=32).scores if method == "multiview" else saliency(
            model, method).scores
        assert scores.shape == (4,) and np.isfinite(scores).all() and ((scores >= 0) & (scores <= 1)).all()
    for sequence in explore_object(model, "blind", 3, sensor=SMALL, probes=9, seed=0):
        assert_sequence_sane(sequence, SMALL)
        assert_on_surface(model, sequence.positions)



# ------------------------------------------------------------------------------------------ huge poses
def test_huge_but_finite_pose_vectors_press_as_their_directions():
    """Normals or tangents of 1e200-1e300 times a unit vector gave all-range frames (the norm overflowed to inf, the
    rays had zero directions): now the frames and sides of the unit vectors, bit for bit; positions beyond the
    largest coordinate a mesh may have are refused."""
    from perception.errors import SensorSpecError

    sphere = primitives.sphere(40.0, 3)
    model = ObjectModel(sphere.vertices, sphere.triangles, name="sphere")
    positions = np.array([[40.0, 0.0, 0.0], [0.0, 0.0, 40.0]])
    normals = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    tangents = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    frames, sides = SMALL.press(model, positions, normals, tangents)
    assert frames.min() < 1.0 < frames.max() < SMALL.range_mm  # pads on the surface, its curve falling away
    for scale_n, scale_t in ((1e200, 1.0), (1e300, 1.0), (1.0, 1e300), (1e300, 1e300)):
        got, got_sides = SMALL.press(model, positions, normals * scale_n, tangents * scale_t)
        np.testing.assert_array_equal(got, frames)
        np.testing.assert_array_equal(got_sides, sides)
    with pytest.raises(SensorSpecError, match="beyond"):
        SMALL.press(model, positions + 1e300, normals, tangents)
