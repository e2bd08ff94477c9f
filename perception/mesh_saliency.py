"""Direct 3D saliency estimators: mesh saliency (Lee, Varshney & Jacobs 2005) and ISS keypoints (Open3D).

Both return per-vertex scores in [0, 1] (V,), float64, deterministic.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from perception.geometry import ObjectModel

#: Lee et al.'s scales: sigma_i = i * epsilon, epsilon = 0.3 % of the object size (ObjectModel.size, pose-free).
LEE_SCALES = (2, 3, 4, 5, 6)
LEE_EPSILON_FRACTION = 0.003
#: ISS keypoints are spread with a Gaussian of this fraction of the object size (2 % = 3 mm at 150 mm).
ISS_SPREAD_FRACTION = 0.02


def _gaussian_means(values: np.ndarray, pairs: np.ndarray, dist: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-weighted mean of ``values`` around every vertex within 2 sigma (the vertex included)."""
    keep = dist < 2 * sigma
    i, j, d = pairs[keep, 0], pairs[keep, 1], dist[keep]
    w = np.exp(-(d * d) / (2 * sigma * sigma))
    n = len(values)
    num = values.copy() + np.bincount(i, w * values[j], n) + np.bincount(j, w * values[i], n)
    den = 1.0 + np.bincount(i, w, n) + np.bincount(j, w, n)
    return num / den


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
    maxima = np.sort(x[_local_maxima(x, edges)])[:-1]
    mean_other = maxima.mean() if maxima.size else 0.0
    return x * (1.0 - mean_other) ** 2


def mesh_saliency(
    model: ObjectModel, scales=LEE_SCALES, epsilon_fraction: float = LEE_EPSILON_FRACTION
) -> np.ndarray:
    """Lee, Varshney & Jacobs (2005) mesh saliency per vertex, in [0, 1].

    For each scale sigma_i = i * epsilon (epsilon = ``epsilon_fraction`` of the object size):
    the centre-surround difference |G(H, sigma) - G(H, 2 sigma)| of the Gaussian-weighted mean curvature H
    (neighbours within 2 sigma, Euclidean, from a KD-tree), then the non-linear normalisation, summed over
    scales and scaled to [0, 1]. Uses ``model.curvature.mean``.
    """
    curvature = model.curvature.mean.astype(np.float64)
    epsilon = epsilon_fraction * model.size
    radius = 4 * max(scales) * epsilon  # 2 * (2 sigma_max): the widest surround
    tree = cKDTree(model.vertices)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    dist = np.linalg.norm(model.vertices[pairs[:, 0]] - model.vertices[pairs[:, 1]], axis=1)
    total = np.zeros(model.n_vertices)
    for i in scales:
        sigma = i * epsilon
        fine = _gaussian_means(curvature, pairs, dist, sigma)
        coarse = _gaussian_means(curvature, pairs, dist, 2 * sigma)
        total += _lee_normalize(np.abs(fine - coarse), model.edges)
    top = total.max()
    return total / top if top > 0 else total


def iss_keypoints(model: ObjectModel) -> np.ndarray:
    """Indices of the vertices Open3D's ISS detector (Zhong 2009) picks, with its default radii and ratios."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.vertices))
    keypoints = np.asarray(o3d.geometry.keypoint.compute_iss_keypoints(cloud).points)
    if len(keypoints) == 0:
        return np.zeros(0, dtype=np.int64)
    # The keypoints are copies of input points: the nearest vertex is exact.
    _, index = cKDTree(model.vertices).query(keypoints)
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
