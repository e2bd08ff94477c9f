"""Direct 3D saliency estimators: mesh saliency (Lee, Varshney & Jacobs 2005) and ISS keypoints (Open3D).

Both return per-vertex scores in [0, 1] (V,), float64, deterministic.

Mesh saliency averages over every vertex's neighbours within 7.2 % of the object size; their number grows with
the square of the vertex count (80,000 vertices: 33 million pairs). The neighbours are therefore found and used a
block of vertices at a time (:func:`neighbourhood_sums`), each block holding at most :data:`BLOCK_PAIRS` pairs
(fewer when the memory limit ``VISUOTACTILE_MAX_MEMORY_MB`` is lower), so the memory it takes is bounded
whatever the mesh; a mesh one of whose vertices alone has more neighbours than the limit allows is refused. A
progress bar over the blocks appears when the sums run long (:data:`PROGRESS_DELAY_S`).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel
from perception.limits import check_bytes, limit
from perception.runtime import progress_bar

#: Lee et al.'s scales: sigma_i = i * epsilon, epsilon = 0.3 % of the object size (ObjectModel.size, pose-free).
LEE_SCALES = (2, 3, 4, 5, 6)
LEE_EPSILON_FRACTION = 0.003
#: ISS keypoints are spread with a Gaussian of this fraction of the object size (2 % = 3 mm at 150 mm).
ISS_SPREAD_FRACTION = 0.02
#: Bytes held per neighbour pair while a block is processed: the KD-tree's (i, j, distance) records (24, built
#: then handed over), global indices and the recomputed distance (24), one Gaussian's mask, weights and gathered
#: values (about 30), rounded up.
PAIR_BYTES = 96
#: Neighbour pairs per block at most (64 MiB of pairs); fewer when the ``memory_mb`` limit is lower.
BLOCK_PAIRS = (64 << 20) // PAIR_BYTES
#: Seconds the neighbourhood sums run before their progress bar appears: a short run prints nothing.
PROGRESS_DELAY_S = 5.0


def _local_maxima(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Vertices whose value is >= every 1-ring neighbour's."""
    neighbour_max = np.full(len(values), -np.inf)
    np.maximum.at(neighbour_max, edges[:, 0], values[edges[:, 1]])
    np.maximum.at(neighbour_max, edges[:, 1], values[edges[:, 0]])
    return values >= neighbour_max


def _lee_normalize(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Lee et al.'s non-linear suppression: scale to [0, 1], times (max - mean of other local maxima)^2."""
    top = values.max()
    if top <= 0:
        return np.zeros_like(values)
    x = values / top
    # Maxima of x rounded to 1e-4: on a plateau (a cylinder's side) the 1e-7 differences that turning the object
    # leaves would otherwise pick which vertices count, and with them the normalisation.
    maxima = np.sort(x[_local_maxima(np.round(x, 4), edges)])[:-1]
    mean_other = maxima.mean() if maxima.size else 0.0
    return x * (1.0 - mean_other) ** 2


def plan_blocks(vertices: np.ndarray, radius: float, *, where: str = "mesh") -> tuple[cKDTree, list[np.ndarray]]:
    """A KD-tree of ``vertices`` and the vertices cut into blocks whose neighbours within ``radius`` (mm) fit
    :data:`BLOCK_PAIRS` pairs and the ``memory_mb`` limit (:mod:`perception.limits`); the blocks follow the tree's
    leaf order, so each is compact in space. Counting allocates nothing per pair.

    Raises:
        InvalidArgumentError: one vertex alone has more neighbours than the memory limit can hold (``where``
            named, with the limit and its variable).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    n = len(vertices)
    tree = cKDTree(vertices)
    counts = np.asarray(tree.query_ball_point(vertices, radius, return_length=True), dtype=np.int64)
    widest = int(counts.max()) if n else 0
    check_bytes(widest * PAIR_BYTES,
                f"{where}: mesh saliency ({n:,} vertices, up to {widest:,} within {radius:.3g} mm of one vertex)")
    budget = max(widest, min(BLOCK_PAIRS, limit("memory_mb") * 2**20 // PAIR_BYTES))
    ends = np.cumsum(counts[tree.indices])
    blocks, start = [], 0
    while start < n:
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + budget, side="right")))
        blocks.append(tree.indices[start:stop])
        start = stop
    return tree, blocks


def _argsort_small(keys: np.ndarray, top: int) -> np.ndarray:
    """Stable argsort of integer ``keys`` in [0, top): least significant 16 bits first (numpy sorts 16-bit keys by
    radix, several times faster than a comparison sort of 64-bit ones)."""
    order = np.argsort(keys.astype(np.uint16), kind="stable")
    shift = 16
    while top > 1 << shift:
        order = order[np.argsort((keys[order] >> shift).astype(np.uint16), kind="stable")]
        shift += 16
    return order


def neighbourhood_sums(
    values: np.ndarray,
    vertices: np.ndarray,
    sigmas,
    *,
    where: str = "mesh",
    plan: tuple[cKDTree, list[np.ndarray]] | None = None,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian sums over each vertex's neighbourhood, for several sigmas (mm), in bounded memory.

    For every sigma s and vertex i: ``num[s, i]`` = sum over the vertices j with |v_i - v_j| < 2 s (i itself
    included) of w_ij values_j, and ``den[s, i]`` = sum of w_ij, with w_ij = exp(-|v_i - v_j|^2 / 2 s^2); their
    ratio is the Gaussian-weighted mean of Lee et al. The neighbours within the widest 2 s are listed one block
    of vertices at a time (``plan``, default :func:`plan_blocks`). Each vertex's terms are added in a fixed order
    (by cut-off, then by neighbour index), so the sums do not depend on the blocks, to the bit. Returns two
    (len(sigmas), V) float64 arrays, rows in the order of ``sigmas``.

    ``progress``: a bar over the blocks (:func:`perception.runtime.progress_bar`), which appears only once the
    sums have taken :data:`PROGRESS_DELAY_S` seconds (a large mesh), so that short runs print nothing.

    Raises:
        InvalidArgumentError: sigmas not positive and finite, mismatched shapes, or sums or one vertex's
            neighbours that the memory limit cannot hold.
    """
    values = np.asarray(values, dtype=np.float64)
    vertices = np.asarray(vertices, dtype=np.float64)
    n = len(vertices)
    given = np.asarray(sigmas, dtype=np.float64).ravel()
    if not len(given) or not np.isfinite(given).all() or given.min() <= 0 or len(given) > 1000:
        raise InvalidArgumentError(f"{where}: sigmas must be 1 to 1000 positive finite lengths (mm), got {sigmas!r}")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or values.shape != (n,):
        raise InvalidArgumentError(f"{where}: expected (V, 3) vertices and (V,) values, got shapes {vertices.shape} "
                                   f"and {values.shape}")
    rank = np.argsort(given, kind="stable")
    sigmas = [float(s) for s in given[rank]]
    cutoffs = 2 * given[rank]
    check_bytes(len(sigmas) * n * 8, f"{where}: mesh saliency sums ({n:,} vertices x {len(sigmas)} sigmas)")
    tree, blocks = plan if plan is not None else plan_blocks(vertices, cutoffs[-1], where=where)
    num = np.tile(values, (len(sigmas), 1))  # the vertex itself, weight 1
    den = np.ones((len(sigmas), n))
    for block in progress_bar(blocks, enabled=progress, desc=f"mesh saliency {where}", unit="block",
                              delay=PROGRESS_DELAY_S):
        found = cKDTree(vertices[block]).sparse_distance_matrix(tree, cutoffs[-1], output_type="ndarray")
        local, j, dist = found["i"], found["j"], found["v"]
        del found
        # A fixed order of each vertex's terms (Lee's local-maximum test turns last-bit differences on symmetric
        # meshes into visible ones): by the first cut-off that keeps the pair (so that each sigma takes a prefix
        # of the arrays), then by neighbour index.
        order = _argsort_small(j, n)
        order = order[block[local[order]] != j[order]]  # the vertex itself is counted above
        local, j, dist = local[order], j[order], dist[order]
        # The cut-offs fall on |v_i - v_j| computed as in numpy (sqrt of the summed squares), whatever the tree's
        # own arithmetic: pairs within a rounding error of a cut-off are measured again.
        first = np.searchsorted(cutoffs, dist, side="right")  # the pair is kept by sigma k iff first <= k
        gap = np.minimum(np.abs(dist - cutoffs[np.maximum(first - 1, 0)]),
                         np.abs(cutoffs[np.minimum(first, len(cutoffs) - 1)] - dist))
        near = np.flatnonzero(gap <= 1e-9 * cutoffs[-1])
        del gap
        if len(near):
            diff = vertices[block[local[near]]] - vertices[j[near]]
            dist[near] = np.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2])
            first[near] = np.searchsorted(cutoffs, dist[near], side="right")
        order = np.argsort(first.astype(np.uint16), kind="stable")
        local, dist, terms = local[order], dist[order], values[j[order]]
        ends = np.searchsorted(first[order], np.arange(len(sigmas)), side="right")
        del order, j, first
        for k, sigma in enumerate(sigmas):
            d = dist[: ends[k]]
            w = np.exp(-(d * d) / (2 * sigma * sigma))
            num[k, block] += np.bincount(local[: ends[k]], w * terms[: ends[k]], len(block))
            den[k, block] += np.bincount(local[: ends[k]], w, len(block))
    back = np.argsort(rank)  # the rows in the order the sigmas were given
    return num[back], den[back]


def mesh_saliency(
    model: ObjectModel, scales=LEE_SCALES, epsilon_fraction: float = LEE_EPSILON_FRACTION, *, progress: bool = True
) -> np.ndarray:
    """Lee, Varshney & Jacobs (2005) mesh saliency per vertex, in [0, 1].

    For each scale sigma_i = i * epsilon (epsilon = ``epsilon_fraction`` of the object size):
    the centre-surround difference |G(H, sigma) - G(H, 2 sigma)| of the Gaussian-weighted mean curvature H
    (neighbours within 2 sigma, Euclidean, from a KD-tree), then the non-linear normalisation, summed over
    scales and scaled to [0, 1]. Uses ``model.curvature.mean``. The neighbourhoods are summed a block of
    vertices at a time (:func:`neighbourhood_sums`): memory stays bounded whatever the vertex count. ``progress``:
    their bar, shown once they have run :data:`PROGRESS_DELAY_S` seconds (500,000 triangles take minutes).

    Raises:
        InvalidArgumentError: a mesh so dense that one vertex's neighbourhood alone does not fit the memory limit
            (``VISUOTACTILE_MAX_MEMORY_MB``), checked before the curvature is computed, or so large that its
            per-vertex sums (8 bytes x 8 sigmas per vertex) do not.
    """
    epsilon = epsilon_fraction * model.size
    fine = {i: i * epsilon for i in scales}
    coarse = {i: 2 * fine[i] for i in scales}
    sigmas = sorted(set(fine.values()) | set(coarse.values()))
    # Planned, and refused if need be, before the curvature: the slow part on a large mesh.
    plan = plan_blocks(model.vertices, 2 * max(sigmas), where=model.name)
    curvature = model.curvature.mean.astype(np.float64)
    num, den = neighbourhood_sums(curvature, model.vertices, sigmas, where=model.name, plan=plan,
                                  progress=progress)
    means = dict(zip(sigmas, num / den, strict=True))
    total = np.zeros(model.n_vertices)
    for i in scales:
        total += _lee_normalize(np.abs(means[fine[i]] - means[coarse[i]]), model.edges)
    top = total.max()
    return total / top if top > 0 else total


def iss_keypoints(model: ObjectModel) -> np.ndarray:
    """Indices of the vertices Open3D's ISS detector (Zhong 2009) picks, with its default radii and ratios, on the
    vertices in the object's pose-free frame rounded to 1e-6 mm: a regular mesh holds exact ties among the ratios
    ISS compares, which the rounding noise of another pose would otherwise break one way or the other."""
    local = np.round(model.to_scene(model.vertices), 6)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(local))
    keypoints = np.asarray(o3d.geometry.keypoint.compute_iss_keypoints(cloud).points)
    if len(keypoints) == 0:
        return np.zeros(0, dtype=np.int64)
    # The keypoints are copies of input points: the nearest vertex is exact.
    _, index = cKDTree(local).query(keypoints)
    return np.unique(index)


def iss_saliency(model: ObjectModel, spread_fraction: float = ISS_SPREAD_FRACTION) -> np.ndarray:
    """ISS baseline per vertex, in [0, 1]: 1 at each ISS keypoint, decaying as exp(-d^2 / 2 s^2) with the
    Euclidean distance d to the nearest keypoint, s = ``spread_fraction`` of the object size. All zero when ISS
    finds no keypoint."""
    index = iss_keypoints(model)
    if len(index) == 0:
        return np.zeros(model.n_vertices)
    d, _ = cKDTree(model.vertices[index]).query(model.vertices)
    s = spread_fraction * model.size
    return np.exp(-(d * d) / (2 * s * s))
