"""Mesh saliency (Lee et al. 2005) in bounded memory: the neighbour sums are made a block of vertices at a time.

Checked: the block sums against a dense distance matrix (an independent method), distances exactly on a cut-off
included; the scores against the former all-pairs implementation (``query_pairs`` over the whole mesh, reproduced
below) and against Lee et al.'s formulas computed by brute force (all V^2 distances, loops); the scores do not
depend on the blocks (memory limit) to the bit; memory stays near the limit; a
mesh whose single vertex's neighbourhood does not fit the limit is refused, naming it, before its curvature is
computed; the progress bar shows when asked and the run is long, and not otherwise.
"""

from __future__ import annotations

import tracemalloc
from collections import defaultdict

import numpy as np
import pytest
from scipy.spatial import cKDTree

from perception import mesh_saliency as mesh_saliency_module
from perception import primitives, runtime
from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel
from perception.mesh_saliency import (
    LEE_EPSILON_FRACTION,
    LEE_SCALES,
    _lee_normalize,
    mesh_saliency,
    neighbourhood_sums,
    plan_blocks,
)
from perception.saliency import saliency
from perception.shapes import make_object

MEMORY_ENV = "VISUOTACTILE_MAX_MEMORY_MB"


def brute_force_mesh_saliency(model: ObjectModel, epsilon_fraction: float = LEE_EPSILON_FRACTION) -> np.ndarray:
    """Lee, Varshney & Jacobs (2005) from the paper's formulas, by brute force: all V^2 distances, a row at a time,
    G(H, s)_i = sum_{|v_i - v_j| < 2s} H_j exp(-d_ij^2 / 2s^2) / sum_{|v_i - v_j| < 2s} exp(-d_ij^2 / 2s^2), the
    saliency |G(H, s) - G(H, 2s)| at s = 2..6 epsilon, each scaled to [0, 1] and multiplied by (1 - m)^2, m the mean
    of its local maxima (1-ring, on the values rounded to 1e-4 as the module does) other than the global one, then
    summed (a scale that is 0 everywhere adds nothing) and scaled to [0, 1]. Written with loops over the vertices,
    independent of the module's blocks."""
    curvature = model.curvature.mean.astype(np.float64)
    ring = defaultdict(set)
    for a, b in model.edges:
        ring[a].add(b)
        ring[b].add(a)
    epsilon = epsilon_fraction * model.size
    sigmas = sorted({i * epsilon for i in LEE_SCALES} | {2 * i * epsilon for i in LEE_SCALES})
    mean = {sigma: np.zeros(model.n_vertices) for sigma in sigmas}
    for v, point in enumerate(model.vertices):  # one row of the V x V distance matrix at a time
        d = np.linalg.norm(model.vertices - point, axis=1)
        for sigma in sigmas:
            w = np.where(d < 2 * sigma, np.exp(-d**2 / (2 * sigma**2)), 0.0)
            mean[sigma][v] = (w @ curvature) / w.sum()
    total = np.zeros(model.n_vertices)
    for i in LEE_SCALES:
        s = np.abs(mean[i * epsilon] - mean[2 * i * epsilon])
        if s.max() == 0:  # no vertex has a neighbour at this scale: nothing to add
            continue
        s = s / s.max()
        key = np.round(s, 4)
        maxima = sorted(s[v] for v in range(len(s)) if all(key[v] >= key[u] for u in ring[v]))[:-1]
        total += s * (1 - (np.mean(maxima) if maxima else 0.0)) ** 2
    return total / total.max()


def gaussian_means(values: np.ndarray, pairs: np.ndarray, dist: np.ndarray, sigma: float) -> np.ndarray:
    """The former implementation's Gaussian-weighted mean of ``values`` around every vertex within 2 sigma (the
    vertex included), from every unordered pair (i < j) and its distance at once."""
    keep = dist < 2 * sigma
    i, j, d = pairs[keep, 0], pairs[keep, 1], dist[keep]
    w = np.exp(-(d * d) / (2 * sigma * sigma))
    n = len(values)
    num = values.copy() + np.bincount(i, w * values[j], n) + np.bincount(j, w * values[i], n)
    den = 1.0 + np.bincount(i, w, n) + np.bincount(j, w, n)
    return num / den


def all_pairs_mesh_saliency(model: ObjectModel) -> np.ndarray:
    """The former implementation, which held every pair within the widest surround at once."""
    curvature = model.curvature.mean.astype(np.float64)
    epsilon = LEE_EPSILON_FRACTION * model.size
    pairs = cKDTree(model.vertices).query_pairs(4 * max(LEE_SCALES) * epsilon, output_type="ndarray")
    dist = np.linalg.norm(model.vertices[pairs[:, 0]] - model.vertices[pairs[:, 1]], axis=1)
    total = np.zeros(model.n_vertices)
    for i in LEE_SCALES:
        sigma = i * epsilon
        fine = gaussian_means(curvature, pairs, dist, sigma)
        coarse = gaussian_means(curvature, pairs, dist, 2 * sigma)
        total += _lee_normalize(np.abs(fine - coarse), model.edges)
    return total / total.max() if total.max() > 0 else total


def bumpy_sphere(subdivisions: int = 4) -> ObjectModel:
    """An icosphere with smooth radial bumps: no symmetry, so no two vertices tie in Lee's local-maximum test."""
    s = primitives.sphere(40.0, subdivisions)
    u = s.vertices / np.linalg.norm(s.vertices, axis=1, keepdims=True)
    bumps = 1 + 0.06 * np.sin(5 * u[:, 0] + 1) * np.cos(4 * u[:, 1]) + 0.03 * np.sin(9 * u[:, 2])
    return ObjectModel(s.vertices * bumps[:, None], s.triangles, name="bumpy-sphere")


def bumpy_torus() -> ObjectModel:
    """A torus with bumps that break its rotational symmetry."""
    t = primitives.torus(40.0, 15.0, 48, 24)
    x, y, z = t.vertices.T
    angle = np.arctan2(y, x)
    bumps = 1 + 0.04 * np.sin(3 * angle + 0.5) + 0.02 * np.cos(5 * angle) * np.sin(z / 7)
    return ObjectModel(t.vertices * bumps[:, None], t.triangles, name="bumpy-torus")


def dense_patch(k: int = 150) -> ObjectModel:
    """A k x k grid in a 1 mm square and one triangle 150 mm away: every grid vertex lies within the widest
    surround (7.2 % of the ~200 mm size) of every other, k^2 neighbours each."""
    u, v = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k), indexing="ij")
    grid = np.stack([u.ravel(), v.ravel(), np.zeros(k * k)], axis=1)
    index = np.arange(k * k).reshape(k, k)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    triangles = np.vstack([np.stack([a, b, c], 1), np.stack([a, c, d], 1), [[k * k, k * k + 1, k * k + 2]]])
    far = np.array([[150.0, 0.0, 0.0], [150.0, 1.0, 0.0], [150.0, 0.0, 1.0]])
    return ObjectModel(np.vstack([grid, far]), triangles, name="dense-patch")


class TestNeighbourhoodSums:
    def test_against_a_dense_distance_matrix(self, monkeypatch):
        """num = W values and den = W 1 with W_ij = exp(-d^2 / 2 s^2) for d < 2 s (the diagonal included), computed
        from the full V x V distance matrix; a coincident pair of vertices counts with weight 1. Summation order is
        the only difference: 1e-12 of the sum of the terms' magnitudes covers a few hundred terms (about 1e-14)."""
        rng = np.random.default_rng(3)
        points = rng.uniform(-10.0, 10.0, (400, 3))
        points[7] = points[3]  # two vertices at one place
        values = rng.normal(size=400)
        sigmas = [3.0, 1.0, 2.0]  # rows come back in the order given
        dense = np.linalg.norm(points[:, None] - points[None], axis=2)
        for limit_mb in (None, "1"):
            if limit_mb:
                monkeypatch.setenv(MEMORY_ENV, limit_mb)
            num, den = neighbourhood_sums(values, points, sigmas)
            for k, sigma in enumerate(sigmas):
                w = np.where(dense < 2 * sigma, np.exp(-(dense**2) / (2 * sigma**2)), 0.0)
                np.testing.assert_allclose(den[k], w.sum(axis=1), rtol=1e-12)
                assert np.all(np.abs(num[k] - w @ values) <= 1e-12 * (w @ np.abs(values)))  # terms of both signs
        assert den[1, 3] >= 2.0 and den[1, 7] >= 2.0  # each of the coincident pair counts the other at weight 1

    def test_distances_on_a_cut_off_are_left_out(self):
        """A unit grid: many distances fall exactly on a cut-off 2 s (2, 4, 5 mm) or a rounding error from one
        (2 sqrt 2); the neighbourhood is |v_i - v_j| < 2 s, strictly, as the dense matrix has it."""
        points = np.stack(np.meshgrid(np.arange(25.0), np.arange(25.0), [0.0, 1.0], indexing="ij"), -1).reshape(-1, 3)
        values = np.random.default_rng(5).normal(size=len(points))
        sigmas = [1.0, 2.0, 2.5, np.sqrt(2.0)]
        dense = np.linalg.norm(points[:, None] - points[None], axis=2)
        num, den = neighbourhood_sums(values, points, sigmas)
        for k, sigma in enumerate(sigmas):
            w = np.where(dense < 2 * sigma, np.exp(-(dense**2) / (2 * sigma**2)), 0.0)
            np.testing.assert_allclose(den[k], w.sum(axis=1), rtol=1e-12)
            assert np.all(np.abs(num[k] - w @ values) <= 1e-12 * (w @ np.abs(values)))

    def test_blocks_keep_to_the_memory_limit(self, monkeypatch):
        monkeypatch.setenv(MEMORY_ENV, "1")
        model = bumpy_sphere(4)
        radius = 4 * max(LEE_SCALES) * LEE_EPSILON_FRACTION * model.size
        tree, blocks = plan_blocks(model.vertices, radius)
        assert len(blocks) > 1
        np.testing.assert_array_equal(np.sort(np.concatenate(blocks)), np.arange(model.n_vertices))
        for block in blocks:  # pairs per block, counted by brute force
            pairs = sum(len(tree.query_ball_point(p, radius)) for p in model.vertices[block])
            assert pairs * 96 <= 2**20


class TestMeshSaliency:
    @pytest.mark.parametrize("make", [lambda: make_object("mug", 1), lambda: bumpy_sphere(4),
                                      bumpy_torus], ids=["mug", "bumpy", "torus"])
    def test_same_scores_as_the_all_pairs_implementation(self, make):
        """The Gaussian means agree to about 1e-15 (the same terms, summed in another order); the scores divide
        centre-surround differences by their maximum, which can amplify that by a few orders: 1e-9 on scores in
        [0, 1] still catches any change of cut-off or weight (those move scores by more than 1e-4). The meshes have
        no exact symmetry: on a symmetric mesh (a box, a regular torus) Lee's local-maximum test compares values
        equal but for rounding, and either implementation's choice is as good as the other."""
        model = make()
        np.testing.assert_allclose(mesh_saliency(model), all_pairs_mesh_saliency(model), rtol=0, atol=1e-9)

    @pytest.mark.parametrize(("make", "epsilon_fraction"), [(lambda: bumpy_sphere(4), LEE_EPSILON_FRACTION),
                                                            (lambda: bumpy_sphere(4), 0.01), (bumpy_torus, 0.015)],
                             ids=["bumpy", "bumpy-wide", "torus-wide"])
    def test_same_scores_as_the_formulas_by_brute_force(self, make, epsilon_fraction):
        """Lee et al.'s formulas on all V^2 distances: the same to 1e-9 (summation order only, amplified by the
        normalisation as above), the same most salient vertices. These meshes are coarse for Lee's epsilon (the
        finest scales hold the vertex alone): wider scales give every vertex from a few to some 200 neighbours."""
        model = make()
        scores = mesh_saliency(model, epsilon_fraction=epsilon_fraction)
        expected = brute_force_mesh_saliency(model, epsilon_fraction)
        np.testing.assert_allclose(scores, expected, rtol=0, atol=1e-9)
        assert np.array_equal(np.argsort(-scores, kind="stable")[:20], np.argsort(-expected, kind="stable")[:20])

    @pytest.mark.parametrize("name", ["box", "mug"])
    def test_scores_do_not_depend_on_the_memory_limit(self, name, monkeypatch):
        """To the bit, symmetric box included: each vertex's terms are summed in one order whatever the blocks."""
        model = make_object(name, 0)
        default = mesh_saliency(model)
        monkeypatch.setenv(MEMORY_ENV, "1")
        assert len(plan_blocks(model.vertices, 0.072 * model.size)[1]) > 10
        np.testing.assert_array_equal(mesh_saliency(model), default)

    def test_memory_stays_near_the_limit(self, monkeypatch):
        """10,242 vertices, 270,000 pairs within the widest surround: all at once they took 17 MB (numpy
        allocations, tracemalloc); with a 1 MB limit the blocks take at most 1 MB and the per-vertex sums 16 x 8
        bytes per vertex (1.3 MB)."""
        model = primitives.sphere(40.0, 5)
        _ = model.curvature.mean, model.edges, model.size  # computed outside the measurement (cached on the model)
        monkeypatch.setenv(MEMORY_ENV, "1")
        tracemalloc.start()
        try:
            scores = mesh_saliency(model)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert peak < 2**20 + 256 * model.n_vertices  # 3.6 MB
        assert np.isfinite(scores).all() and scores.max() == 1.0

    def test_a_neighbourhood_beyond_the_limit_is_refused_before_the_curvature(self, monkeypatch):
        """22,500 vertices within 1 mm: one vertex's 22,500 neighbours (2 MB of pairs) do not fit 1 MB. Refused
        naming the mesh, the limit and its variable; the curvature (the slow part) is never computed."""
        model = dense_patch()
        monkeypatch.setenv(MEMORY_ENV, "1")
        with pytest.raises(InvalidArgumentError, match=r"dense-patch: mesh saliency \(22,503 vertices, up to 22,500 "
                                                       r"within .* mm of one vertex\) would take 2 MB, above the limit of "
                                                       r"1 MB .*VISUOTACTILE_MAX_MEMORY_MB"):
            saliency(model, "mesh")
        assert "curvature" not in model.__dict__


def test_sums_do_not_depend_on_how_the_neighbours_are_listed():
    """Each vertex's terms are added in a fixed order: another KD-tree (which lists neighbours in another order) gives
    the same sums to the bit; Lee's local-maximum test would turn last-bit differences on symmetric meshes (the
    box) into visible ones."""
    for name in ("box", "mug"):
        model = make_object(name, 0)
        values = model.curvature.mean.astype(np.float64)
        sigmas = [0.9, 1.8, 3.6]
        _, blocks = plan_blocks(model.vertices, 2 * max(sigmas))
        other = cKDTree(model.vertices, leafsize=3, balanced_tree=False, compact_nodes=False)
        a = neighbourhood_sums(values, model.vertices, sigmas, plan=(cKDTree(model.vertices), blocks))
        b = neighbourhood_sums(values, model.vertices, sigmas, plan=(other, blocks))
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True)), name


class TestProgress:
    @pytest.fixture(autouse=True)
    def bars_allowed(self, monkeypatch):
        """Bars on, as on a terminal session: the environment and the process switch allow them."""
        monkeypatch.setenv(runtime.PROGRESS_ENV, "1")
        monkeypatch.setattr(runtime, "_progress", None)

    def test_a_short_run_shows_no_bar(self, capsys):
        """The default asks for a bar, which appears only once the sums have run PROGRESS_DELAY_S seconds."""
        model = bumpy_sphere(3)
        mesh_saliency(model)
        assert capsys.readouterr().err == ""

    def test_a_bar_over_the_blocks_when_asked_and_long(self, monkeypatch, capsys):
        """With no delay (every run counts as long) the bar counts the blocks, named after the mesh; progress=False
        shows none; the scores are the same either way."""
        model = bumpy_sphere(4)
        monkeypatch.setenv(MEMORY_ENV, "1")
        monkeypatch.setattr(mesh_saliency_module, "PROGRESS_DELAY_S", 0.0)
        blocks = len(plan_blocks(model.vertices, 4 * max(LEE_SCALES) * LEE_EPSILON_FRACTION * model.size)[1])
        assert blocks > 1
        quiet = mesh_saliency(model, progress=False)
        assert capsys.readouterr().err == ""
        shown = mesh_saliency(model, progress=True)
        err = capsys.readouterr().err
        assert "mesh saliency bumpy-sphere" in err and f"{blocks}/{blocks}" in err
        np.testing.assert_array_equal(shown, quiet)

    def test_the_process_switch_turns_the_bar_off(self, monkeypatch, capsys):
        monkeypatch.setattr(mesh_saliency_module, "PROGRESS_DELAY_S", 0.0)
        runtime.set_progress(False)
        try:
            mesh_saliency(bumpy_sphere(3), progress=True)
        finally:
            runtime.set_progress(None)
        assert capsys.readouterr().err == ""
