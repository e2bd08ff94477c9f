"""Synthetic tactile batches with analytic geometry, for the fusion tests."""

from __future__ import annotations

import numpy as np

from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor


def rotation(seed: int) -> np.ndarray:
    """A random proper rotation matrix (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def circle_batch(radii, probes: int = 12, grid=(4, 4), seed: int = 0, labels=None, plane_normals=None):
    """Great circles of spheres of the given radii (mm) centred at the origin, one sequence per radius.

    Each circle lies in a random plane through the centre; normals are radial, tangents along the circle.
    Frames hold the radius (so a classifier can tell them apart), pad sides 20 mm.
    """
    rng = np.random.default_rng(seed)
    radii = np.asarray(radii, dtype=np.float64)
    n = len(radii)
    angles = 2 * np.pi * np.arange(probes) / probes
    positions, normals, tangents, plane_normal_list = [], [], [], []
    for i, radius in enumerate(radii):
        m = rng.normal(size=3) if plane_normals is None else np.asarray(plane_normals[i], dtype=float)
        m /= np.linalg.norm(m)
        u = np.cross(m, [1.0, 0.0, 0.0] if abs(m[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(m, u)
        radial = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v
        positions.append(radius * radial)
        normals.append(radial)
        tangents.append(-np.sin(angles)[:, None] * u + np.cos(angles)[:, None] * v)
        plane_normal_list.append(m)
    frames = np.broadcast_to(radii[:, None, None, None], (n, probes, *grid)).astype(np.float32)
    labels = np.zeros(n, dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64)
    return SequenceBatch(
        frames=frames.copy(),
        normals=np.array(normals, dtype=np.float32),
        positions=np.array(positions, dtype=np.float32),
        tangents=np.array(tangents, dtype=np.float32),
        pad_sides_mm=np.full((n, probes), 20.0, dtype=np.float32),
        plane_points=np.zeros((n, 3)),
        plane_normals=np.array(plane_normal_list),
        labels=labels,
        object_ids=np.arange(n, dtype=np.int64),
        class_names=tuple(f"c{k}" for k in range(int(labels.max()) + 1)),
        object_names=tuple(f"o{k}" for k in range(n)),
        sensor_spec=FSRSensor(rows=grid[0], cols=grid[1]).spec(),
    )
