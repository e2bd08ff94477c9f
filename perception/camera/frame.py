"""The RGB-D frame every camera source yields: colour, depth in mm, pinhole intrinsics, camera pose.

Conventions (the OAK / OpenCV ones): the camera looks along +z, x to the right, y down; pixel (u, v) =
(column, row) with pixel centres at integer coordinates; ``depth_mm`` is the z distance along the optical
axis (not the ray length), 0 where the camera has no depth. ``pose`` maps camera coordinates (mm) to world
coordinates (mm); it is the identity when unknown.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from perception.errors import InvalidArgumentError

#: Farthest camera distance, mm (10 m): an OAK-D's depth is meaningless far beyond it, and a distance near the
#: float range overflows the pose arithmetic (here, not in :mod:`perception.camera.virtual`, so that checking a
#: command line does not load Open3D).
MAX_DISTANCE_MM = 10_000.0


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the (colour-aligned) depth image.

    Attributes:
        fx, fy: focal lengths, pixels.
        cx, cy: principal point, pixels (column, row).
        width, height: image size, pixels.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(values)) or self.fx <= 0 or self.fy <= 0:
            raise InvalidArgumentError(f"intrinsics: focal lengths must be finite and positive, got {values}")
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 1 or self.height < 1:
            raise InvalidArgumentError(f"intrinsics: image size must be positive integers, got {self.width} x {self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def matrix(self) -> np.ndarray:
        """The 3 x 3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}

    @classmethod
    def from_matrix(cls, matrix, width: int, height: int) -> Intrinsics:
        k = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
        return cls(fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], width=width, height=height)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution (pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5, width, height
        )


@dataclass(frozen=True, eq=False)
class RGBDFrame:
    """One colour + depth capture, depth registered to the colour image.

    Attributes:
        color: (H, W, 3) uint8 RGB.
        depth_mm: (H, W) float32 z depth, mm; 0 where there is no depth.
        intrinsics: the pinhole :class:`Intrinsics` of both images.
        pose: 4 x 4 camera-to-world transform (rotation + translation in mm); identity when unknown.
        timestamp_s: capture time, seconds (0 when unknown).
        name: where the frame came from (file, device, ``virtual:<object>``).

    Raises:
        InvalidArgumentError: shapes that disagree with each other or with the intrinsics, negative or
            non-finite depth, or a pose that is not a finite rigid transform.
    """

    color: np.ndarray
    depth_mm: np.ndarray
    intrinsics: Intrinsics
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    timestamp_s: float = 0.0
    name: str = "frame"

    def __post_init__(self) -> None:
        color = np.asarray(self.color)
        depth = np.asarray(self.depth_mm)
        k = self.intrinsics
        if color.ndim == 2:  # a grey image: replicate to RGB
            color = np.repeat(color[:, :, None], 3, axis=2)
        if color.shape != (k.height, k.width, 3):
            raise InvalidArgumentError(
                f"{self.name}: colour must be ({k.height}, {k.width}, 3) to match the intrinsics, got {color.shape}"
            )
        if depth.shape != (k.height, k.width):
            raise InvalidArgumentError(
                f"{self.name}: depth must be ({k.height}, {k.width}) to match the intrinsics, got {depth.shape}"
            )
        if color.dtype != np.uint8:
            raise InvalidArgumentError(f"{self.name}: colour must be uint8, got {color.dtype}")
        depth = depth.astype(np.float32)
        if not np.isfinite(depth).all() or (depth < 0).any():
            raise InvalidArgumentError(f"{self.name}: depth must be finite and >= 0 mm (0 = no depth)")
        pose = np.asarray(self.pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise InvalidArgumentError(f"{self.name}: pose must be a finite 4 x 4 matrix, got shape {pose.shape}")
        r = pose[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or not np.allclose(pose[3], [0, 0, 0, 1]):
            raise InvalidArgumentError(f"{self.name}: pose must be a rigid transform (rotation + translation)")
        for array in (color, depth, pose):
            array.setflags(write=False)
        object.__setattr__(self, "color", color)
        object.__setattr__(self, "depth_mm", depth)
        object.__setattr__(self, "pose", pose)

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool, True where there is depth."""
        return self.depth_mm > 0

    @property
    def camera_position(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, mm."""
        return self.pose[:3, 3].copy()

    def points(self, mask: np.ndarray | None = None, *, world: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Back-project the pixels with depth (and ``mask``) to 3D.

        Returns (N, 3) float64 points in mm (world frame when ``world``, else camera frame) and their
        (N, 3) float64 RGB colours in [0, 1], row-major over the image.
        """
        k = self.intrinsics
        keep = self.valid if mask is None else (self.valid & np.asarray(mask, dtype=bool))
        rows, cols = np.nonzero(keep)
        z = self.depth_mm[rows, cols].astype(np.float64)
        pts = np.stack([(cols - k.cx) * z / k.fx, (rows - k.cy) * z / k.fy, z], axis=1)
        if world:
            pts = pts @ self.pose[:3, :3].T + self.pose[:3, 3]
        return pts, self.color[rows, cols].astype(np.float64) / 255.0
