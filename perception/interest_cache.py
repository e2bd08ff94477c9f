"""Interest points found before: a store's record or an on-disk cache, usable wherever sampling wants a Saliency.

Several stores of the same objects (other sensors, probe counts or contour counts: the experiments' run-time
part makes eight) would each compute every object's saliency again; :class:`InterestPointCache` keeps the
points of each (mesh, method, seed, count) once. Its key is a digest of the loaded mesh (vertices, triangles,
colours, transform, centering: another pose, scale or repair is another mesh), the method, seed and count, the sources of the
``perception`` package and the versions of the libraries saliency uses (points cached by other code or another
Open3D are computed again). Entries are small ``.npy`` files read
without pickle; one that is damaged, of the wrong shape or not finite is ignored and recomputed.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception import untrusted
from perception.atomic import atomic_path
from perception.errors import SaliencyError
from perception.geometry import ObjectModel

log = logging.getLogger(__name__)

#: An entry larger than this is not an interest-point list (a 10 x 3 float64 file is 368 bytes).
MAX_ENTRY_BYTES = 1 << 16


@dataclass(frozen=True, eq=False)
class KnownInterestPoints:
    """Interest points of ``model`` by ``method`` found before (a store's record, a cache), strongest first."""

    model: ObjectModel
    method: str
    points: np.ndarray

    def interest_points(self, n: int, **_) -> np.ndarray:
        if n > len(self.points):
            raise SaliencyError(f"{self.model.name}: {len(self.points)} interest points are known, {n} asked for")
        return self.points[:n].copy()


#: Libraries whose results saliency depends on (rendering and ray casting, filters, ranks, repairs): another
#: version of one may move the interest points, so it is another cache key.
SALIENCY_LIBRARIES = ("numpy", "scipy", "open3d", "pymeshlab")


@functools.cache
def code_version() -> str:
    """A digest of the ``perception`` package's Python sources and of the versions of :data:`SALIENCY_LIBRARIES`
    (:func:`perception.runtime.sources_digest`; read once per process)."""
    from perception.runtime import sources_digest

    return sources_digest({"perception": Path(__file__).resolve().parent}, SALIENCY_LIBRARIES)


class InterestPointCache:
    """Interest points on disk under ``folder``, by mesh content, method, seed and count (module docstring)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def key(self, model: ObjectModel, method: str, seed: int, n: int) -> str:
        # Everything of the model that saliency can read (colours feed the colour channels); not its name.
        h = hashlib.blake2b(digest_size=16)
        for array in (model.vertices, model.triangles, model.vertex_colors, model.transform):
            if array is None:
                h.update(b"none")
                continue
            a = np.ascontiguousarray(array)
            h.update(repr((a.dtype.str, a.shape)).encode())
            h.update(a.data)
        h.update(repr((model.centering, method, int(seed), int(n), code_version())).encode())
        return h.hexdigest()

    def _path(self, key: str) -> Path:
        return self.folder / f"{key}.npy"

    def get(self, model: ObjectModel, method: str, seed: int, n: int) -> np.ndarray | None:
        """The cached (n, 3) points (mm), or None when absent or unusable. Only a small regular file is opened
        (never blocking: a FIFO or device is skipped), and its header is checked before any array is read."""
        path = self._path(self.key(model, method, seed, n))
        try:
            f = untrusted.open_regular(path, MAX_ENTRY_BYTES)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            log.warning("%s: unusable interest-point cache entry (%s); computing again", path, exc)
            return None
        try:
            with f:
                version = np.lib.format.read_magic(f)
                if version not in ((1, 0), (2, 0)):
                    raise ValueError(f".npy format version {version}")
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, fortran, dtype = read_header(f)
                if shape != (n, 3) or dtype != np.dtype("<f8") or fortran:
                    raise ValueError(f"holds {shape} {dtype}, not {n} x 3 float64")
                f.seek(0)  # read_array reads the header again
                points = np.lib.format.read_array(f, allow_pickle=False)
        except (OSError, ValueError, MemoryError) as exc:
            log.warning("%s: unusable interest-point cache entry (%s); computing again", path, exc)
            return None
        if points.shape != (n, 3) or not np.isfinite(points).all():
            log.warning("%s: cache entry is not %d finite points; computing again", path, n)
            return None
        return points

    def put(self, model: ObjectModel, method: str, seed: int, points: np.ndarray) -> None:
        """Keep ``points`` (n, 3); a write that fails is logged, never raised (the cache only saves time)."""
        points = np.asarray(points, dtype=np.float64)
        path = self._path(self.key(model, method, seed, len(points)))
        try:
            os.makedirs(self.folder, exist_ok=True)
            with atomic_path(path) as tmp, open(tmp, "wb") as f:
                np.save(f, points, allow_pickle=False)
        except OSError as exc:
            log.warning("%s: could not cache interest points (%s)", path, exc)

    def known(self, model: ObjectModel, method: str, seed: int, n: int) -> KnownInterestPoints | None:
        """The cached points as a :class:`KnownInterestPoints`, or None."""
        points = self.get(model, method, seed, n)
        return None if points is None else KnownInterestPoints(model, method, points)


__all__ = ["MAX_ENTRY_BYTES", "SALIENCY_LIBRARIES", "InterestPointCache", "KnownInterestPoints", "code_version"]
