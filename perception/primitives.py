"""Analytic test surfaces in millimetres, with their exact normals and curvatures.

Used by tests and benchmarks as known answers: every function returns an :class:`ObjectModel` with the
surface's vertices exactly on the analytic shape, and the ``analytic_*`` helpers give the exact normal and
curvature at any point of it (outward normals; convex -> positive mean curvature).
These are not scaled to 150 mm: their size is the one asked for.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from perception.geometry import ObjectModel


def _model(vertices: np.ndarray, triangles: np.ndarray, name: str) -> ObjectModel:
    return ObjectModel(np.asarray(vertices, dtype=np.float64), np.asarray(triangles), name=name)


def sphere(radius_mm: float = 50.0, subdivisions: int = 4) -> ObjectModel:
    """Icosphere: an icosahedron subdivided ``subdivisions`` times, vertices projected onto the sphere.

    Vertex count 10 * 4**subdivisions + 2 (subdivisions 3 -> 642, 5 -> 10242, 6 -> 40962).
    """
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(radius=1.0)
    if subdivisions > 0:
        mesh = mesh.subdivide_midpoint(number_of_iterations=subdivisions)
    v = np.asarray(mesh.vertices)
    v = radius_mm * v / np.linalg.norm(v, axis=1, keepdims=True)
    return _model(v, np.asarray(mesh.triangles), f"sphere_r{radius_mm:g}_s{subdivisions}")


def ellipsoid(axes_mm=(60.0, 40.0, 30.0), subdivisions: int = 4) -> ObjectModel:
    """Icosphere scaled to semi-axes ``axes_mm`` (a, b, c) along x, y, z."""
    unit = sphere(1.0, subdivisions)
    return _model(unit.vertices * np.asarray(axes_mm), unit.triangles, f"ellipsoid_s{subdivisions}")


def _grid_triangles(n_u: int, n_v: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Two triangles per cell of an n_u x n_v vertex grid (index u * n_v + v), optionally wrapping."""
    cu = n_u if wrap_u else n_u - 1
    cv = n_v if wrap_v else n_v - 1
    u, v = np.meshgrid(np.arange(cu), np.arange(cv), indexing="ij")
    u, v = u.ravel(), v.ravel()
    a = u * n_v + v
    b = ((u + 1) % n_u) * n_v + v
    c = ((u + 1) % n_u) * n_v + (v + 1) % n_v
    d = u * n_v + (v + 1) % n_v
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def torus(major_mm: float = 50.0, minor_mm: float = 20.0, n_major: int = 64, n_minor: int = 32) -> ObjectModel:
    """Torus around z with tube radius ``minor_mm`` whose centre circle has radius ``major_mm``."""
    theta = 2 * np.pi * np.arange(n_major) / n_major
    phi = 2 * np.pi * np.arange(n_minor) / n_minor
    t, p = np.meshgrid(theta, phi, indexing="ij")
    r = major_mm + minor_mm * np.cos(p)
    v = np.stack([r * np.cos(t), r * np.sin(t), minor_mm * np.sin(p)], -1).reshape(-1, 3)
    # theta grows counter-clockwise around z, phi outward-then-up: (u, v) order gives outward normals.
    return _model(v, _grid_triangles(n_major, n_minor, True, True), f"torus_{n_major}x{n_minor}")


def cylinder(radius_mm: float = 30.0, height_mm: float = 100.0, n_around: int = 64, n_along: int = 32) -> ObjectModel:
    """Closed cylinder around z (side, plus two fan caps), centred at the origin."""
    theta = 2 * np.pi * np.arange(n_around) / n_around
    z = np.linspace(-height_mm / 2, height_mm / 2, n_along)
    t, zz = np.meshgrid(theta, z, indexing="ij")
    side = np.stack([radius_mm * np.cos(t), radius_mm * np.sin(t), zz], -1).reshape(-1, 3)
    tri = _grid_triangles(n_around, n_along, True, False)  # (theta, z) order winds outward
    bottom, top = len(side), len(side) + 1
    ring_lo = np.arange(n_around) * n_along
    ring_hi = ring_lo + n_along - 1
    nxt = np.roll(np.arange(n_around), -1)
    caps = np.concatenate(
        [np.stack([np.full(n_around, bottom), ring_lo[nxt], ring_lo], 1),
         np.stack([np.full(n_around, top), ring_hi, ring_hi[nxt]], 1)]
    )
    v = np.vstack([side, [[0, 0, -height_mm / 2], [0, 0, height_mm / 2]]])
    return _model(v, np.vstack([tri, caps]), f"cylinder_{n_around}x{n_along}")


def plane(side_mm: float = 100.0, n: int = 21) -> ObjectModel:
    """Flat square in z = 0 with normal +z (an open mesh), centred at the origin."""
    x = np.linspace(-side_mm / 2, side_mm / 2, n)
    xx, yy = np.meshgrid(x, x, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
    return _model(v, _grid_triangles(n, n, False, False), f"plane_{side_mm:g}")


def hollow_hemisphere(
    radius_mm: float = 30.0, thickness_mm: float = 4.0, n_around: int = 96, n_polar: int = 48
) -> ObjectModel:
    """A bowl: the lower half of a spherical shell (outer radius ``radius_mm``), open side up (+z), closed rim.

    Its inside is concave: a pad pressed there cannot lie flat, so the adaptive FSR pad must shrink.
    """
    inner = radius_mm - thickness_mm
    theta = 2 * np.pi * np.arange(n_around) / n_around
    polar = np.linspace(np.pi / 2, np.pi, n_polar)[:-1]  # equator (rim) down to just above the pole

    def shell(r: float) -> np.ndarray:
        t, p = np.meshgrid(theta, polar, indexing="ij")
        pts = np.stack([np.sin(p) * np.cos(t), np.sin(p) * np.sin(t), np.cos(p)], -1).reshape(-1, 3)
        return r * pts

    outer_v, inner_v = shell(radius_mm), shell(inner)
    n_ring = n_polar - 1
    grid = _grid_triangles(n_around, n_ring, True, False)
    outer_t = grid[:, ::-1]
    inner_t = grid + len(outer_v)
    poles = len(outer_v) + len(inner_v) + np.array([0, 1])
    nxt = np.roll(np.arange(n_around), -1)
    last = np.arange(n_around) * n_ring + n_ring - 1
    first = np.arange(n_around) * n_ring
    off = len(outer_v)
    tris = [
        outer_t,
        inner_t,
        np.stack([np.full(n_around, poles[0]), last[nxt], last], 1),  # outer bottom cap
        np.stack([np.full(n_around, poles[1]), last + off, last[nxt] + off], 1),  # inner bottom cap
        np.stack([first, first[nxt], first[nxt] + off], 1),  # rim
        np.stack([first, first[nxt] + off, first + off], 1),
    ]
    v = np.vstack([outer_v, inner_v, [[0, 0, -radius_mm], [0, 0, -inner]]])
    model = _model(v, np.vstack(tris), "hollow_hemisphere")
    return _orient_outward(model)


def _orient_outward(model: ObjectModel) -> ObjectModel:
    """Flip all triangles if the signed volume is negative (closed meshes only)."""
    v0, v1, v2 = (model.vertices[model.triangles[:, i]] for i in range(3))
    volume = np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0
    if volume < 0:
        return _model(model.vertices, model.triangles[:, ::-1], model.name)
    return model


# ------------------------------------------------------------------------------- analytic answers
def analytic_sphere(points: np.ndarray, radius_mm: float):
    """Outward normals and (mean, Gaussian) curvature of a sphere centred at the origin."""
    n = points / np.linalg.norm(points, axis=1, keepdims=True)
    return n, np.full(len(points), 1.0 / radius_mm), np.full(len(points), 1.0 / radius_mm**2)


def analytic_ellipsoid(points: np.ndarray, axes_mm):
    """Outward normals and (mean, Gaussian) curvature of the ellipsoid x^2/a^2 + y^2/b^2 + z^2/c^2 = 1."""
    a, b, c = axes_mm
    x, y, z = points.T
    grad = np.stack([x / a**2, y / b**2, z / c**2], 1)
    n = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    s = x**2 / a**4 + y**2 / b**4 + z**2 / c**4
    gauss = 1.0 / (a * b * c) ** 2 / s**2
    mean = (x**2 + y**2 + z**2 - a**2 - b**2 - c**2) / (2 * (a * b * c) ** 2 * s**1.5)
    return n, -mean, gauss


def analytic_torus(points: np.ndarray, major_mm: float, minor_mm: float):
    """Outward normals and (mean, Gaussian) curvature of the torus around z."""
    rho = np.hypot(points[:, 0], points[:, 1])
    centre = np.stack([points[:, 0] * major_mm / rho, points[:, 1] * major_mm / rho, np.zeros(len(rho))], 1)
    n = points - centre
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos_phi = (rho - major_mm) / minor_mm
    k_tube = 1.0 / minor_mm
    k_ring = cos_phi / rho
    return n, 0.5 * (k_tube + k_ring), k_tube * k_ring


def analytic_cylinder(points: np.ndarray, radius_mm: float):
    """Outward normals and (mean, Gaussian) curvature of the cylinder side around z."""
    n = np.stack([points[:, 0], points[:, 1], np.zeros(len(points))], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n, np.full(len(points), 0.5 / radius_mm), np.zeros(len(points))
