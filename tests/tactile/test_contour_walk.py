"""The section walk, the cyclic shift and Toucher's pair order against independent answers: a brute-force walk,
np.roll, exact shoelace areas and the pair order's documented rule."""

from __future__ import annotations

import numpy as np
import pytest

from tactile import contours


# ------------------------------------------------------------------------------- contours
def _reference_loops(edges: np.ndarray) -> list[tuple[list[int], list[int], bool]]:
    """Loops of a graph whose every node has two edges, brute force: from the first unused edge (a, b) in edge
    order, a then b, then at each node the other edge that touches it, until back at a."""
    edges = [tuple(e) for e in np.asarray(edges).tolist()]
    used = [False] * len(edges)
    walks = []
    for first, (a, b) in enumerate(edges):
        if used[first]:
            continue
        used[first] = True
        nodes, path, node, edge = [a], [first], b, first
        while node != a:
            nodes.append(node)
            (edge,) = [e for e, pair in enumerate(edges) if e != edge and node in pair]
            used[edge] = True
            path.append(edge)
            node = edges[edge][1] if edges[edge][0] == node else edges[edge][0]
        walks.append((nodes, path, True))
    return walks


@pytest.mark.parametrize("seed", range(6))
def test_loop_walk_starts_each_loop_at_its_first_unused_edge_from_a_to_b(seed):
    rng = np.random.default_rng(seed)
    sizes = rng.integers(3, 9, rng.integers(1, 5))
    labels = rng.permutation(int(sizes.sum()))
    edges, at = [], 0
    for size in sizes:
        ring = labels[at:at + size].tolist()
        at += size
        edges += [(ring[i], ring[(i + 1) % size]) for i in range(size)]
    edges = np.array(edges)[rng.permutation(len(edges))]
    flip = rng.random(len(edges)) < 0.5
    edges[flip] = edges[flip][:, ::-1]
    assert contours._walk(edges, int(sizes.sum())) == _reference_loops(edges)


def test_section_chains_of_a_closed_mesh_follow_the_reference_walk():
    from perception.shapes import make_object

    model = make_object("ring", 0)
    rng = np.random.default_rng(0)
    for _ in range(10):
        plane = contours.Plane(model.center, rng.normal(size=3))
        d = contours._signed_distances(model, plane)
        nodes, edges, _ = contours._segments(model, d)
        if not (np.bincount(edges.ravel(), minlength=len(nodes)) == 2).all():
            continue
        expected = _reference_loops(edges)
        assert contours._walk(edges, len(nodes)) == expected
        chains = contours.section_chains(model, plane)
        assert [len(c.points) for c in chains] == [len(w[0]) for w in expected]


def test_signed_area_is_taken_about_the_plane_point_far_from_the_origin():
    # A unit square (counter-clockwise about +z) 1e9 mm from the origin, the plane through one of its corners:
    # about the plane's point the shoelace sum is exact; about the origin it loses every digit.
    far = 1e9
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64) + [far, far, 0]
    plane = contours.Plane(np.array([far, far, 0.0]), np.array([0.0, 0.0, 1.0]))
    assert contours.signed_area(square, plane) == 1.0
    assert contours.signed_area(square[::-1], plane) == -1.0


@pytest.mark.parametrize("k", [0, 1, 2, 6])
def test_shifted_is_np_roll(k):
    a = np.arange(21).reshape(7, 3)
    assert np.array_equal(contours._shifted(a, k), np.roll(a, -k, axis=0))
    assert np.array_equal(contours._shifted(a[:, 0]), np.roll(a[:, 0], -1))


# ------------------------------------------------------------------------------- Toucher.pair_order
@pytest.fixture(scope="module")
def guided_toucher():
    import perception.saliency as attention
    from perception.shapes import make_object
    from tactile.touching import Toucher

    model = make_object("mug", 3)
    return Toucher(model, "guided", probes=6, saliency=attention.saliency(model, "multiview"))


def test_pair_order_follows_every_seed_switch_even_past_float_precision(guided_toucher):
    # Seeds 2**53 and 2**53 + 1 are one float; the orders differ (the documented rule: position k of seed s is
    # planes[permutation of (s, k // P)][k % P]).
    toucher = guided_toucher
    for seed in (2**53, 2**53 + 1, 3, np.uint64(2**53 + 1), 4, 3, 2**63 - 1, 2**63 - 2):
        order = toucher.pair_order(seed)
        planes = order.planes
        n = len(planes)
        assert order.seed == int(seed)
        for k in (0, 1, n - 1, n, 2 * n + 1):
            expected = planes[np.random.default_rng([int(seed), k // n]).permutation(n)[k % n]]
            assert order[k] is expected, (seed, k)
