"""Multi-view rendering by ray casting (Open3D ``RaycastingScene``): no OpenGL, no display, no EGL.

Each view is an orthographic camera on a sphere around the object looking at its centre. Orthographic
rays keep the pixel size (mm) the same everywhere, so image-space filters have one physical scale per
view set. Per pixel a :class:`View` holds the hit triangle and its barycentric coordinates, which map any
image value back to the exact surface point it came from (no depth re-projection).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel
from perception.validate import check_count

log = logging.getLogger(__name__)

#: Default number of views. At 128 x 128 every vertex of the torus, cylinder and catalogue ring is hit, and
#: every vertex of the other catalogue objects lies within two pixels of a hit point, except the mug's inner
#: bottom, which no outside view sees (``tests/perception/test_render.py``). Multiview saliency at these defaults:
#: median 0.39 s per 7k-triangle SHREC 2007 mesh on 2 shared cores (``benchmarks.saliency``), 0.05 s of it rendering.
DEFAULT_N_VIEWS = 20
DEFAULT_SIZE_PX = 128
#: The image side covers the sphere about the centre holding the object (diameter ObjectModel.size) plus this margin.
_MARGIN = 1.04


@dataclass(frozen=True)
class Camera:
    """An orthographic camera: pixel (row, col) -> ray ``origin(row, col) + t * forward``.

    Attributes:
        position: (3,) unit vector from the object centre to the camera (its place on the view sphere).
        center: (3,) the point the camera looks at, mm.
        forward: (3,) unit viewing direction (``-position``).
        right, up: (3,) unit image axes; columns grow along ``right``, rows grow along ``-up``.
        width, height: image size, pixels.
        pixel_mm: side of one pixel on the image plane, mm.
        distance_mm: distance from the image plane to ``center`` along ``forward``, mm.
    """

    position: np.ndarray
    center: np.ndarray
    forward: np.ndarray
    right: np.ndarray
    up: np.ndarray
    width: int
    height: int
    pixel_mm: float
    distance_mm: float

    def rays(self, model: ObjectModel | None = None) -> np.ndarray:
        """(H * W, 6) float32 rays (origin, unit direction), row-major over pixels, in ``model``'s scene frame
        (:meth:`ObjectModel.to_scene`, computed in float64) to cast into ``model.scene``, else in world mm."""
        rows, cols = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        x = (cols.ravel() + 0.5 - self.width / 2) * self.pixel_mm
        y = (self.height / 2 - rows.ravel() - 0.5) * self.pixel_mm
        origins = (self.center - self.distance_mm * self.forward) + np.outer(x, self.right) + np.outer(y, self.up)
        forward = self.forward
        if model is not None:
            origins, forward = model.to_scene(origins), model.to_scene(forward, directions=True)
        return np.hstack([origins, np.broadcast_to(forward, origins.shape)]).astype(np.float32)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates (col, row), continuous, of (N, 3) points in mm (no visibility test)."""
        rel = np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.center
        col = rel @ self.right / self.pixel_mm + self.width / 2 - 0.5
        row = self.height / 2 - rel @ self.up / self.pixel_mm - 0.5
        return np.stack([col, row], axis=1)


@dataclass(frozen=True)
class View:
    """One rendered view. Background pixels have ``mask`` False, ``triangle_ids`` -1 and zeros elsewhere.

    Attributes:
        depth: (H, W) float32 distance from the image plane to the surface along the ray, mm.
        mask: (H, W) bool, True where a ray hit the mesh.
        normal: (H, W, 3) float32 world-frame unit normal, interpolated from the hit triangle's vertex normals.
        intensity: (H, W) float32 Lambertian shading in [0, 1] from a headlight (light along the view ray).
        color: (H, W, 3) float32 RGB in [0, 1] interpolated from vertex colours, or None without colours.
        triangle_ids: (H, W) int32 hit triangle, -1 where nothing was hit.
        barycentric: (H, W, 3) float32 weights of the hit triangle's three vertices (sum 1 on hits).
        camera: the :class:`Camera`.
    """

    depth: np.ndarray
    mask: np.ndarray
    normal: np.ndarray
    intensity: np.ndarray
    color: np.ndarray | None
    triangle_ids: np.ndarray
    barycentric: np.ndarray
    camera: Camera


def view_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (Fibonacci lattice), deterministic.

    Raises:
        InvalidArgumentError: ``n`` is not an integer >= 1.
    """
    n = check_count(n, "n", "view_directions")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i  # golden angle
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def make_camera(
    model: ObjectModel, position: np.ndarray, width: int, height: int, frame: np.ndarray | None = None
) -> Camera:
    """An orthographic camera at unit direction ``position`` from the centre, framing the whole object.

    The image's up direction follows the first column of ``frame`` (a (3, 3) rotation, default the world axes
    with z first), or its second column when looking along the first: with the object's principal frame the
    images do not depend on how the object is posed."""
    position = np.asarray(position, dtype=np.float64)
    position = position / np.linalg.norm(position)
    forward = -position
    axes = np.eye(3)[:, [2, 0, 1]] if frame is None else np.asarray(frame, dtype=np.float64)
    hint = axes[:, 0] if abs(forward @ axes[:, 0]) < 0.9 else axes[:, 1]
    right = np.cross(forward, hint)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    extent = _MARGIN * model.size
    return Camera(
        position=position,
        center=model.center.copy(),
        forward=forward,
        right=right,
        up=up,
        width=int(width),
        height=int(height),
        pixel_mm=extent / min(width, height),
        distance_mm=model.size,  # every vertex lies within size / 2 of the centre: start outside that sphere
    )


@dataclass(frozen=True)
class ViewStack:
    """Rendered views stacked along a first axis (N views), the arrays :class:`View` holds one slice of.

    Attributes: as :class:`View`, each with a leading (N,) axis (``color`` None without colours), and
    ``cameras``, the N :class:`Camera` objects.
    """

    depth: np.ndarray
    mask: np.ndarray
    normal: np.ndarray
    intensity: np.ndarray
    color: np.ndarray | None
    triangle_ids: np.ndarray
    barycentric: np.ndarray
    cameras: list[Camera]

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def views(self) -> list[View]:
        """The N :class:`View` objects; their arrays are views into the stack's (no copies)."""
        return [
            View(
                depth=self.depth[k],
                mask=self.mask[k],
                normal=self.normal[k],
                intensity=self.intensity[k],
                color=None if self.color is None else self.color[k],
                triangle_ids=self.triangle_ids[k],
                barycentric=self.barycentric[k],
                camera=cam,
            )
            for k, cam in enumerate(self.cameras)
        ]


def _stacked_rays(model: ObjectModel, cameras: list[Camera]) -> np.ndarray:
    """(N * H * W, 6) float32 rays of N cameras of one image size, camera after camera: the rows of
    ``np.concatenate([c.rays(model) for c in cameras])``, the same values, built without a per-camera loop."""
    cam0 = cameras[0]
    rows, cols = np.meshgrid(np.arange(cam0.height), np.arange(cam0.width), indexing="ij")
    x = (cols.ravel() + 0.5 - cam0.width / 2) * cam0.pixel_mm
    y = (cam0.height / 2 - rows.ravel() - 0.5) * cam0.pixel_mm
    base = np.stack([c.center - c.distance_mm * c.forward for c in cameras])
    right = np.stack([c.right for c in cameras])
    up = np.stack([c.up for c in cameras])
    origins = (base[:, None, :] + x[None, :, None] * right[:, None, :]) + y[None, :, None] * up[:, None, :]
    forward = model.to_scene(np.stack([c.forward for c in cameras]), directions=True)
    rays = np.empty((len(cameras), len(x), 6), dtype=np.float32)
    for k in range(len(cameras)):  # one view at a time: one large (M, 3) @ (3, 3) product is far slower
        rays[k, :, :3] = model.to_scene(origins[k])
    rays[:, :, 3:] = forward[:, None, :]
    return rays.reshape(-1, 6)


def render_stack(
    model: ObjectModel,
    n_views: int = DEFAULT_N_VIEWS,
    width: int = DEFAULT_SIZE_PX,
    height: int = DEFAULT_SIZE_PX,
    *,
    directions: np.ndarray | None = None,
    frame: np.ndarray | None = None,
) -> ViewStack:
    """Render ``n_views`` orthographic views of ``model`` in one ``cast_rays`` call, stacked (:class:`ViewStack`).

    Args:
        model: the object.
        n_views: number of views, on a Fibonacci sphere (ignored when ``directions`` is given).
        width, height: image size in pixels.
        directions: optional (K, 3) camera positions (unit vectors from the centre).
        frame: optional (3, 3) rotation fixing each image's up direction (see :func:`make_camera`).

    Raises:
        InvalidArgumentError: non-positive or fractional image size or view count, or directions that are not
            finite non-zero 3-vectors (also a ``ValueError``).
    """
    width = check_count(width, "width", model.name)
    height = check_count(height, "height", model.name)
    if directions is None:
        dirs = view_directions(check_count(n_views, "n_views", model.name))
    else:
        dirs = np.asarray(directions, dtype=np.float64)
        if dirs.size == 0 or dirs.size % 3 or not np.isfinite(dirs).all() or (np.abs(dirs.reshape(-1, 3)).max(axis=1) == 0).any():
            raise InvalidArgumentError(f"{model.name}: view directions must be finite non-zero 3-vectors, got shape {dirs.shape}")
    cameras = [make_camera(model, d, width, height, frame) for d in dirs.reshape(-1, 3)]
    hits = model.scene.cast_rays(o3d.core.Tensor(_stacked_rays(model, cameras)))
    shape = (len(cameras), height, width)
    t_hit = hits["t_hit"].numpy()
    mask = np.isfinite(t_hit)
    # Shading is computed on the hit pixels only; the background stays zero (ids -1).
    hit = np.flatnonzero(mask)
    ids = hits["primitive_ids"].numpy()[hit].astype(np.int64)
    uv = hits["primitive_uvs"].numpy()[hit].astype(np.float64)
    # Open3D: point = (1 - u - v) * v0 + u * v1 + v * v2.
    bary = np.column_stack([1.0 - uv.sum(axis=1), uv])
    corners = model.triangles[ids]
    normal = np.einsum("nk,nkj->nj", bary, model.vertex_normals[corners])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 1e-12)
    forward = np.stack([c.forward for c in cameras])[hit // (width * height)]
    # Headlight: |cos| so that meshes with flipped normals still shade.
    intensity = np.abs(np.einsum("nj,nj->n", normal, forward))

    def scatter(values: np.ndarray, dtype: type, fill: float = 0) -> np.ndarray:
        out = np.full((mask.size, *values.shape[1:]), fill, dtype=dtype)
        out[hit] = values
        return out.reshape(*shape, *values.shape[1:])

    color = None
    if model.has_colors:
        color = scatter(np.clip(np.einsum("nk,nkj->nj", bary, model.vertex_colors[corners]), 0, 1), np.float32)
    log.debug("%s: rendered %d views of %d x %d", model.name, len(cameras), width, height)
    return ViewStack(
        depth=scatter(t_hit[hit], np.float32),
        mask=mask.reshape(shape),
        normal=scatter(normal, np.float32),
        intensity=scatter(intensity, np.float32),
        color=color,
        triangle_ids=scatter(ids, np.int32, -1),
        barycentric=scatter(bary, np.float32),
        cameras=cameras,
    )


def render_views(
    model: ObjectModel,
    n_views: int = DEFAULT_N_VIEWS,
    width: int = DEFAULT_SIZE_PX,
    height: int = DEFAULT_SIZE_PX,
    *,
    directions: np.ndarray | None = None,
    frame: np.ndarray | None = None,
) -> list[View]:
    """Render ``n_views`` orthographic views of ``model`` (one ``cast_rays`` call for all of them): the views of
    :func:`render_stack` (same arguments and errors)."""
    return render_stack(model, n_views, width, height, directions=directions, frame=frame).views


def surface_points(model: ObjectModel, view: View | ViewStack, where: np.ndarray | None = None) -> np.ndarray:
    """(K, 3) float64 exact surface points (barycentric blend of the hit triangle), mm, of the hit pixels
    selected by the bool ``where`` ((H, W) for a view, (N, H, W) for a stack; all hit pixels when None), in
    row-major order (a stack: view after view)."""
    select = view.mask if where is None else (view.mask & where)
    corners = model.vertices[model.triangles[view.triangle_ids[select]]]  # (K, 3, 3)
    return np.einsum("kc,kcj->kj", view.barycentric[select].astype(np.float64), corners)


def vertex_coverage(model: ObjectModel, views: list[View]) -> np.ndarray:
    """(V,) number of views in which each vertex belongs to at least one hit triangle."""
    counts = np.zeros(model.n_vertices, dtype=np.int64)
    for view in views:
        tri = np.unique(view.triangle_ids[view.mask])
        seen = np.zeros(model.n_vertices, dtype=bool)
        seen[model.triangles[tri].ravel()] = True
        counts += seen
    return counts


def interpolate_values(model: ObjectModel, view: View, values: np.ndarray) -> np.ndarray:
    """(H, W) per-vertex ``values`` (V,) blended over each pixel's hit triangle; 0 on the background."""
    values = np.asarray(values, dtype=np.float64)
    corners = values[model.triangles[np.maximum(view.triangle_ids, 0)]]  # (H, W, 3)
    return (view.barycentric * corners).sum(axis=-1) * view.mask


def visible(view: View, points: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """(N,) True where a point (mm) projects inside the image and no surface lies in front of it."""
    cam = view.camera
    pix = np.rint(cam.project(points)).astype(np.int64)
    inside = (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
    col, row = np.clip(pix[:, 0], 0, cam.width - 1), np.clip(pix[:, 1], 0, cam.height - 1)
    depth = (
        np.asarray(points, dtype=np.float64) - (cam.center - cam.distance_mm * cam.forward)
    ) @ cam.forward
    return inside & view.mask[row, col] & (depth <= view.depth[row, col] + tolerance_mm)
