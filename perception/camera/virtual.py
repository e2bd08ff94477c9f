"""A virtual OAK-D: RGB-D frames of an :class:`ObjectModel` standing on a table, by ray casting (Open3D).

Geometry of an OAK-D (Luxonis): stereo baseline 75 mm, mono focal length 882.5 px at 1280 x 800
(441.25 px in the 640 x 400 mode); depth aligned to the colour camera, which sits between the two mono
cameras. The frame is rendered from the colour camera's centre; the stereo model then:

- keeps depth only where the surface point is seen by *both* mono cameras (at -B/2 and +B/2 along the
  camera's x axis): occluded pixels beside depth edges have no depth, as on the device;
- converts depth to disparity d = f B / Z (px), adds Gaussian matching noise (``disparity_sigma_px``) and
  quantises to the subpixel step 1 / 2**``subpixel_bits``, so depth error grows as Z^2: sigma_Z = Z^2 sigma_d / (f B);
- drops pixels beyond the disparity search range (d > ``max_disparity_px``: closer than the minimum range
  f B / max_disparity, 348 mm in 400p, 697 mm in 800p, 348 mm in 800p with extended disparity) and
  pixels whose 3 x 3 neighbourhood spans a depth jump of more than ``edge_jump`` (relative): the matching
  window straddles the edge there;
- reports depth as whole millimetres (uint16 on the device), 0 = no depth.

World frame: table top is the plane z = 0, the object's bounding-box centre is above the origin and its
lowest point touches the table. Cameras look at the object centre. All noise is seeded per view.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from perception.camera.frame import MAX_DISTANCE_MM, Intrinsics, RGBDFrame
from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel

log = logging.getLogger(__name__)

#: OAK-D mono modes: name -> (width, height, focal length px).
OAK_MODES = {"800p": (1280, 800, 882.5), "400p": (640, 400, 441.25)}
OAK_BASELINE_MM = 75.0
#: Disparity search range of the OAK stereo engine, px (doubled by extended disparity).
OAK_MAX_DISPARITY_PX = 95.0

_TABLE_RGB = np.array([0.22, 0.42, 0.36])
_OBJECT_RGB = np.array([0.80, 0.78, 0.72])


@dataclass(frozen=True)
class StereoNoise:
    """Parameters of the stereo depth model (see the module docstring).

    Attributes:
        disparity_sigma_px: standard deviation of the matching noise, px (0: no noise).
        subpixel_bits: fractional bits of the disparity (OAK: 3 to 5).
        max_disparity_px: disparity search range, px.
        edge_jump: relative depth jump in a 3 x 3 neighbourhood above which depth is dropped.
        occlusion: drop pixels that either mono camera cannot see.
    """

    disparity_sigma_px: float = 0.08
    subpixel_bits: int = 3
    max_disparity_px: float = OAK_MAX_DISPARITY_PX
    edge_jump: float = 0.04
    occlusion: bool = True


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """4 x 4 camera-to-world pose of a camera at ``eye`` looking at ``target`` (x right, y down, z forward).

    Raises:
        InvalidArgumentError: eye and target coincide, or the view direction is parallel to ``up``.
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    if not (np.isfinite(eye).all() and np.isfinite(target).all() and np.isfinite(up).all()):
        raise InvalidArgumentError("look_at: eye, target and up must be finite")
    z = target - eye
    with np.errstate(over="ignore", invalid="ignore"):  # a huge eye overflows the norm: refused just below
        norm = np.linalg.norm(z)
    if not np.isfinite(norm):
        raise InvalidArgumentError("look_at: the camera is too far from its target (the distance overflows)")
    if norm == 0:
        raise InvalidArgumentError("look_at: the camera sits on its target")
    z /= norm
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise InvalidArgumentError("look_at: viewing direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


class VirtualOakCamera:
    """Simulated OAK-D captures of ``model`` on a table.

    Args:
        model: the object (mm); it is placed on the table, see :attr:`object_to_world`.
        mode: ``"400p"`` (640 x 400, default) or ``"800p"`` (1280 x 800).
        extended_disparity: double the disparity range (halves the minimum range).
        noise: the :class:`StereoNoise` model; ``None`` gives exact depth (still whole mm, still occlusion).
        table_mm: side of the square table, mm.
        seed: base seed; view ``i`` uses ``(seed, i)``.

    Raises:
        InvalidArgumentError: unknown mode or a non-positive table size.
    """

    def __init__(
        self,
        model: ObjectModel,
        *,
        mode: str = "400p",
        extended_disparity: bool = False,
        noise: StereoNoise | None = StereoNoise(),
        table_mm: float = 800.0,
        seed: int = 0,
    ) -> None:
        if mode not in OAK_MODES:
            raise InvalidArgumentError(f"VirtualOakCamera: unknown mode {mode!r}; choose one of {', '.join(OAK_MODES)}")
        if not table_mm > 0:
            raise InvalidArgumentError(f"VirtualOakCamera: table_mm must be positive, got {table_mm}")
        width, height, focal = OAK_MODES[mode]
        self.model = model
        self.mode = mode
        self.intrinsics = Intrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)
        self.baseline_mm = OAK_BASELINE_MM
        self.noise = noise
        self.max_disparity_px = (noise.max_disparity_px if noise else OAK_MAX_DISPARITY_PX) * (
            2 if extended_disparity else 1
        )
        self.seed = int(seed)
        shift = np.eye(4)
        shift[:3, 3] = [-model.center[0], -model.center[1], -model.bounds[0, 2]]
        #: 4 x 4 map from the model's coordinates to the world (table top z = 0), mm.
        self.object_to_world = shift
        world_vertices = model.vertices + shift[:3, 3]
        #: The object as placed in the world (for reconstruction error), mm.
        self.truth = ObjectModel(world_vertices, model.triangles, name=model.name, label=model.label)
        half = table_mm / 2
        table_v = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(world_vertices.astype(np.float32)), o3d.core.Tensor(model.triangles.astype(np.uint32))
        )
        self._scene.add_triangles(
            o3d.core.Tensor(table_v.astype(np.float32)), o3d.core.Tensor(np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
        )
        self._colors = model.vertex_colors

    @property
    def min_range_mm(self) -> float:
        """Closest depth the stereo engine measures, f B / max disparity, mm."""
        return self.intrinsics.fx * self.baseline_mm / self.max_disparity_px

    @property
    def target(self) -> np.ndarray:
        """The point the orbit cameras look at: the object's centre in the world, mm."""
        return np.array([0.0, 0.0, 0.5 * (self.model.bounds[1, 2] - self.model.bounds[0, 2])])

    def orbit_poses(self, n_views: int, distance_mm: float = 500.0, elevation_deg: float = 35.0) -> list[np.ndarray]:
        """``n_views`` camera poses evenly spaced in azimuth at ``distance_mm`` from the object centre,
        ``elevation_deg`` above the table.

        Raises:
            InvalidArgumentError: n_views < 1, a distance outside (0, :data:`MAX_DISTANCE_MM`], or elevation outside
                (0, 90).
        """
        if int(n_views) != n_views or n_views < 1:
            raise InvalidArgumentError(f"VirtualOakCamera: n_views must be a positive integer, got {n_views!r}")
        if not 0 < distance_mm <= MAX_DISTANCE_MM or not 0 < elevation_deg < 90:
            raise InvalidArgumentError(
                f"VirtualOakCamera: need 0 < distance_mm <= {MAX_DISTANCE_MM:g} and 0 < elevation_deg < 90, got "
                f"{distance_mm}, {elevation_deg}"
            )
        el = np.radians(elevation_deg)
        poses = []
        for az in np.radians(np.arange(n_views) * 360.0 / n_views + 30.0):
            eye = self.target + distance_mm * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            poses.append(look_at(eye, self.target))
        return poses

    def capture_views(
        self, n_views: int, distance_mm: float = 500.0, elevation_deg: float = 35.0
    ) -> list[RGBDFrame]:
        """Frames from :meth:`orbit_poses` (view i seeded with ``(seed, i)``)."""
        return [self.capture(p, i) for i, p in enumerate(self.orbit_poses(n_views, distance_mm, elevation_deg))]

    def _cast(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        rays = np.hstack([origins, directions]).astype(np.float32)
        return {k: v.numpy() for k, v in self._scene.cast_rays(o3d.core.Tensor(rays)).items()}

    def capture(self, pose: np.ndarray, index: int = 0) -> RGBDFrame:
        """One RGB-D frame from the camera-to-world ``pose`` (4 x 4, mm)."""
        k = self.intrinsics
        pose = np.asarray(pose, dtype=np.float64)
        rows, cols = np.meshgrid(np.arange(k.height), np.arange(k.width), indexing="ij")
        d_cam = np.stack([(cols.ravel() - k.cx) / k.fx, (rows.ravel() - k.cy) / k.fy, np.ones(rows.size)], axis=1)
        d_world = d_cam @ pose[:3, :3].T
        origin = pose[:3, 3]
        hit = self._cast(np.broadcast_to(origin, d_world.shape), d_world)
        z = hit["t_hit"].astype(np.float64)  # direction has unit z: t is the z depth
        valid = np.isfinite(z)
        z[~valid] = 0.0
        points = origin + z[:, None] * d_world
        geometry = hit["geometry_ids"].astype(np.int64)
        # Colour: Lambertian shading under a headlight plus ambient light.
        normals = hit["primitive_normals"].astype(np.float64)
        view_dir = d_world / np.linalg.norm(d_world, axis=1, keepdims=True)
        shade = 0.35 + 0.65 * np.abs((normals * view_dir).sum(axis=1))
        albedo = np.where((geometry == 0)[:, None], _OBJECT_RGB, _TABLE_RGB)
        if self._colors is not None:
            on_obj = valid & (geometry == 0)
            tri = self.model.triangles[hit["primitive_ids"][on_obj].astype(np.int64)]
            uv = hit["primitive_uvs"][on_obj].astype(np.float64)
            w = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
            albedo[on_obj] = (self._colors[tri] * w[:, :, None]).sum(axis=1)
        rgb = np.where(valid[:, None], albedo * shade[:, None], 0.85)
        color = np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8).reshape(k.height, k.width, 3)

        rng = np.random.default_rng([self.seed, int(index)])
        depth = self._stereo(z, valid, points, pose, rng).reshape(k.height, k.width)
        return RGBDFrame(color, depth, k, pose, timestamp_s=float(index), name=f"virtual:{self.model.name}/{index}")

    def _stereo(self, z, valid, points, pose, rng) -> np.ndarray:
        k, noise = self.intrinsics, self.noise
        fb = k.fx * self.baseline_mm
        ok = valid & (z > 0)
        if noise is None or noise.occlusion:
            for side in (-0.5, 0.5):
                eye = pose[:3, 3] + side * self.baseline_mm * pose[:3, 0]
                idx = np.nonzero(ok)[0]
                hit = self._cast(np.broadcast_to(eye, (len(idx), 3)), points[idx] - eye)
                seen = hit["t_hit"] >= 1.0 - 1e-3  # direction reaches the point at t = 1
                ok[idx[~seen]] = False
        disparity = np.zeros_like(z)
        disparity[ok] = fb / z[ok]
        if noise is not None:
            disparity[ok] += rng.normal(0.0, noise.disparity_sigma_px, int(ok.sum())) if noise.disparity_sigma_px > 0 else 0
            step = 2.0 ** -noise.subpixel_bits
            disparity = np.rint(disparity / step) * step
        ok &= (disparity > 0) & (disparity <= self.max_disparity_px)
        depth = np.zeros_like(z)
        depth[ok] = np.rint(fb / disparity[ok])
        depth[depth > 65535] = 0
        if noise is not None and noise.edge_jump > 0:
            from scipy import ndimage

            img = depth.reshape(k.height, k.width)
            big = np.where(img > 0, img, np.inf)
            lo = ndimage.minimum_filter(big, size=3)
            hi = ndimage.maximum_filter(img, size=3)
            edge = (img > 0) & ((hi - lo) > noise.edge_jump * img)
            img[edge] = 0
            depth = img.ravel()
        return depth.astype(np.float32)


__all__ = ["OAK_BASELINE_MM", "OAK_MODES", "StereoNoise", "VirtualOakCamera", "look_at"]
