"""Recording folders: RGB-D frames as plain files that replay without a device.

Layout written by :func:`write_recording` (format ``visuotactile-rgbd/1``)::

    <folder>/recording.json            {"format", "frames": [names], "depth_scale", "source"}
    <folder>/<name>.color.png          8-bit RGB
    <folder>/<name>.depth.png          16-bit depth, value = depth_m * depth_scale (1000: millimetres)
    <folder>/<name>.json               intrinsics (fx, fy, cx, cy, width, height), pose (4 x 4, mm), timestamp

:func:`read_recording` also reads single captures from other RGB-D cameras laid out as ``color.png``
(or ``rgb.png``) + ``depth.png`` + ``camera.json`` with ``fx, fy, cx, cy[, depth_scale]`` (Open3D's
convention, depth_m = png / depth_scale), e.g. the GraspNet RealSense capture in the shared data.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from perception import untrusted
from perception.atomic import atomic_path, write_text
from perception.camera.frame import Intrinsics, RGBDFrame
from perception.errors import DatasetError, InvalidArgumentError

log = logging.getLogger(__name__)

FORMAT = "visuotactile-rgbd/1"
INDEX = "recording.json"
_MAX_DEPTH_UNITS = 65535
#: Largest frame metadata or ``camera.json`` read, bytes (ours are under 1 kB: intrinsics, a pose, a timestamp);
#: the index may add :data:`INDEX_BYTES_PER_FRAME` per frame the ``frames`` limit allows. Checked from the file's
#: size before reading: a recording is a file users exchange.
MAX_JSON_BYTES = 2**20
#: Index bytes allowed per frame (a name is at most 200 characters, plus quotes, comma and indentation).
INDEX_BYTES_PER_FRAME = 256


def _check_inside(path: Path, root: Path | None) -> None:
    """Refuse a file of the recording that leads outside its folder ``root`` (resolved), e.g. a symbolic link to
    another file of the system: only files inside the recording folder are read.

    Raises:
        DatasetError: naming the file and where it leads.
    """
    if root is None:
        return
    try:
        target = path.resolve()
    except (OSError, RuntimeError) as exc:  # a symlink loop
        raise DatasetError(f"{path}: cannot resolve ({exc})") from None
    if not target.is_relative_to(root):
        raise DatasetError(f"{path}: leads outside the recording folder (to {target}); a recording's files must "
                           "lie inside its folder")


def _read_png(path: Path, what: str, root: Path | None = None) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    _check_inside(path, root)
    if not path.is_file():
        raise DatasetError(f"{path}: {what} image is missing")
    try:
        with Image.open(path) as image:  # reads the header only: the size is checked before any pixel is decoded
            _check_image_size(path, what, image.size)
            if what == "depth":
                if image.mode not in ("I;16", "I;16B", "I;16L", "I", "L"):
                    raise DatasetError(f"{path}: depth must be a 16-bit single-channel PNG, got mode {image.mode}")
                return np.asarray(image).astype(np.float64)
            return np.asarray(image.convert("RGB"), dtype=np.uint8)
    except Image.DecompressionBombError:  # PIL's own limit, checked in Image.open for the largest images
        from perception.limits import LIMITS, limit

        raise DatasetError(f"{path}: {what} image is larger than the limit of {limit('image_pixels')} pixels per "
                           f"image (set {LIMITS['image_pixels'].env} to raise it; PIL refuses more than "
                           f"{2 * Image.MAX_IMAGE_PIXELS} whatever the limit)") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read {what} image ({type(exc).__name__}: {exc})") from None


#: What a PNG file may hold beyond its pixels stored uncompressed (8 bytes each at most, with a filter byte per row):
#: chunk headers, palettes, text. A larger file is refused before it is decoded.
PNG_SPARE_BYTES = 2**20


def _check_image_size(path: Path, what: str, size: tuple[int, int]) -> None:
    """Refuse an image larger than the ``image_pixels`` limit (and what its float64 copy would take) from its
    header, before decoding: a small PNG can hold a huge image of zeros; and a file larger than its pixels can
    take uncompressed (:data:`PNG_SPARE_BYTES`): a small image can carry gigabytes of other chunks."""
    from perception.limits import check_bytes, check_count

    width, height = size
    check_count("image_pixels", width * height, f"{path}: {what} image of {width} x {height} pixels", DatasetError)
    check_bytes(width * height * 8, f"{path}: decoding the {width} x {height} {what} image", DatasetError)
    most = (width * 8 + 1) * height + PNG_SPARE_BYTES
    if path.stat().st_size > most:
        raise DatasetError(f"{path}: {what} image file of {path.stat().st_size} bytes, more than a {width} x {height} "
                           f"image can take ({most}); refused undecoded")


def _number(meta: dict, key: str, default: float, where: Path, positive: bool = False) -> float:
    """``meta[key]`` as a finite float (``default`` when absent). Raises DatasetError naming the file and key."""
    value = meta.get(key, default)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and bool(np.isfinite(value))
    if not ok or (positive and value <= 0):
        raise DatasetError(f"{where}: {key!r} must be a finite{' positive' if positive else ''} number, got {value!r}")
    return float(value)


#: depth_scale (PNG units per metre) accepted: 1 (metres) to 1e6 (micrometres); 1000 is millimetres.
DEPTH_SCALE_RANGE = (1.0, 1e6)


def _depth_scale(meta: dict, where: Path) -> float:
    scale = _number(meta, "depth_scale", 1000.0, where, positive=True)
    low, high = DEPTH_SCALE_RANGE
    if not low <= scale <= high:
        raise DatasetError(f"{where}: 'depth_scale' must be a finite positive number of PNG units per metre in "
                           f"[{low:g}, {high:g}] (1000: millimetres), got {scale!r}")
    return scale


#: Largest distance of a camera from the world origin a pose may give, mm (1 km): a camera looking at a table
#: is metres from any sensible origin; a farther pose is a unit mix-up or a corrupt file, and puts the points
#: where float arithmetic loses the object (Open3D's Poisson segfaulted on a capture 1e10 mm from the origin).
MAX_POSE_TRANSLATION_MM = 1e6


def _pose(meta: dict, where: Path) -> np.ndarray:
    """``meta["pose"]`` (identity when absent) as a finite 4 x 4 float64 matrix whose translation (mm) is at most
    :data:`MAX_POSE_TRANSLATION_MM` long. Raises DatasetError naming ``where``."""
    value = meta.get("pose")
    if value is None:
        return np.eye(4)
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{where}: pose must be a 4 x 4 matrix of numbers") from None
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise DatasetError(f"{where}: pose must be a finite 4 x 4 matrix, got shape {pose.shape}")
    distance = float(np.linalg.norm(pose[:3, 3]))
    if not distance <= MAX_POSE_TRANSLATION_MM:  # also catches an overflow to inf in the norm
        raise DatasetError(f"{where}: pose translation is {distance:.3g} mm from the origin, beyond "
                           f"{MAX_POSE_TRANSLATION_MM:g} mm (1 km); poses are in millimetres: check the units")
    return pose


def _read_json(path: Path, root: Path | None = None, max_bytes: int = MAX_JSON_BYTES) -> dict:
    """The JSON object in ``path``, a file inside the recording folder ``root``, of at most ``max_bytes``.

    Raises:
        DatasetError: naming the file: outside the folder, too large (from its size, before reading), unreadable,
            not JSON, nested too deeply for the parser, or not an object.
    """
    _check_inside(path, root)
    try:
        data = untrusted.read_json(path, max_bytes)
    except (OSError, ValueError) as exc:  # not a regular file, too large (unread), not JSON, nested too deeply
        raise DatasetError(f"{path}: cannot read JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    return data


def _intrinsics(data: dict, where: Path, width: int, height: int) -> Intrinsics:
    intrinsics = _parse_intrinsics(data, where, width, height)
    # A camera's principal point lies in its image and its field of view is not a pinhole's: values far outside
    # these put every point of the capture at one spot or at infinity, which nothing downstream can use.
    side = max(intrinsics.width, intrinsics.height)
    if not (0 <= intrinsics.cx <= intrinsics.width and 0 <= intrinsics.cy <= intrinsics.height):
        raise DatasetError(f"{where}: principal point ({intrinsics.cx:g}, {intrinsics.cy:g}) lies outside the "
                           f"{intrinsics.width} x {intrinsics.height} image")
    if max(intrinsics.fx, intrinsics.fy) > 100 * side:
        raise DatasetError(f"{where}: focal lengths ({intrinsics.fx:g}, {intrinsics.fy:g}) px are beyond 100 x the "
                           "image size (a field of view under 0.6 degrees)")
    if min(intrinsics.fx, intrinsics.fy) < side / 100:
        raise DatasetError(f"{where}: focal lengths ({intrinsics.fx:g}, {intrinsics.fy:g}) px are below 1/100 of the "
                           f"image size ({side / 100:g} px: a field of view over 178 degrees, which no pinhole has)")
    return intrinsics


def _parse_intrinsics(data: dict, where: Path, width: int, height: int) -> Intrinsics:
    try:
        return Intrinsics(
            fx=float(data["fx"]), fy=float(data["fy"]), cx=float(data["cx"]), cy=float(data["cy"]),
            width=int(data.get("width", width)), height=int(data.get("height", height)),
        )
    except KeyError as exc:
        raise DatasetError(f"{where}: intrinsics lack {exc.args[0]!r} (need fx, fy, cx, cy)") from None
    except (TypeError, ValueError, OverflowError) as exc:  # InvalidArgumentError (the checks) is a ValueError
        raise DatasetError(f"{where}: bad intrinsics ({exc})") from None


def _frame(color_path: Path, depth_path: Path, meta: dict, meta_path: Path, depth_scale: float, name: str,
           root: Path | None = None):
    color = _read_png(color_path, "colour", root)
    raw = _read_png(depth_path, "depth", root)
    if color.shape[:2] != raw.shape:
        raise DatasetError(f"{color_path}: colour {color.shape[:2]} and depth {raw.shape} sizes differ")
    height, width = raw.shape
    intrinsics = _intrinsics(meta, meta_path, width, height)
    if (intrinsics.width, intrinsics.height) != (width, height):
        raise DatasetError(
            f"{meta_path}: intrinsics are for {intrinsics.width} x {intrinsics.height}, images are {width} x {height}"
        )
    if not np.isfinite(depth_scale) or depth_scale <= 0:
        raise DatasetError(f"{meta_path}: depth_scale must be positive (units per metre), got {depth_scale}")
    depth_mm = (raw * (1000.0 / depth_scale)).astype(np.float32)
    pose = _pose(meta, meta_path)
    timestamp_s = _number(meta, "timestamp_s", 0.0, meta_path)
    try:
        return RGBDFrame(color, depth_mm, intrinsics, pose, timestamp_s, name=name)
    except InvalidArgumentError as exc:  # the frame checks: report the file
        raise DatasetError(f"{meta_path}: {exc}") from None


def is_recording(folder: str | Path) -> bool:
    """True when ``folder`` looks like a recording this module reads (ours or a single generic capture)."""
    folder = Path(folder)
    return (folder / INDEX).is_file() or (folder / "camera.json").is_file()


def read_recording(folder: str | Path) -> list[RGBDFrame]:
    """Read all frames of a recording folder (ours, or a generic ``color.png`` + ``depth.png`` + ``camera.json``).

    Only files inside ``folder`` are read (a file that is a symbolic link leading outside it is refused), and JSON
    files are size-checked before reading (:data:`MAX_JSON_BYTES`).

    Raises:
        DatasetError: the folder is missing, of no known layout, or a file is missing, malformed, too large or
            outside the folder.
    """
    from perception.limits import limit

    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such recording folder")
    root = folder.resolve()
    index_path = folder / INDEX
    if index_path.is_file():
        index = _read_json(index_path, root, MAX_JSON_BYTES + INDEX_BYTES_PER_FRAME * limit("frames"))
        if index.get("format") != FORMAT:
            raise DatasetError(f"{index_path}: unknown format {index.get('format')!r} (expected {FORMAT!r})")
        names = index.get("frames")
        if not isinstance(names, list) or not names:
            raise DatasetError(f"{index_path}: the recording lists no frames")
        from perception.limits import check_count

        check_count("frames", len(names), f"{index_path}: frames", DatasetError)
        for name in names:  # plain names of files in this folder: nothing outside it is read
            if not (isinstance(name, str) and re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,199}", name)):
                raise DatasetError(f"{index_path}: frame name {name!r} is not a plain file name in the recording "
                                   "folder (letters, digits, '_', '-', '.')")
        scale = _depth_scale(index, index_path)
        frames = []
        for name in names:
            meta_path = folder / f"{name}.json"
            if not meta_path.is_file():
                raise DatasetError(f"{meta_path}: frame metadata is missing")
            meta = _read_json(meta_path, root)
            frames.append(
                _frame(folder / f"{name}.color.png", folder / f"{name}.depth.png", meta, meta_path, scale,
                       f"{folder.name}/{name}", root)
            )
        return frames
    camera_path = folder / "camera.json"
    if camera_path.is_file():
        meta = _read_json(camera_path, root)
        color_path = next((folder / n for n in ("color.png", "rgb.png") if (folder / n).is_file()), folder / "color.png")
        return [_frame(color_path, folder / "depth.png", meta, camera_path,
                       _depth_scale(meta, camera_path), folder.name, root)]
    raise DatasetError(
        f"{folder}: not a recording (expected {INDEX} written by visuotactile, or color.png + depth.png + camera.json)"
    )


def _listed_frames(folder: Path) -> list[str]:
    """The frame names the recording index in ``folder`` lists (none if there is no readable index)."""
    from perception.limits import limit

    try:
        names = _read_json(folder / INDEX, folder.resolve(), MAX_JSON_BYTES + INDEX_BYTES_PER_FRAME * limit("frames"))
        names = names.get("frames", [])
    except (DatasetError, OSError):
        return []
    return [n for n in names if isinstance(n, str)] if isinstance(names, list) else []


def write_recording(
    folder: str | Path, frames: list[RGBDFrame], *, depth_scale: float = 1000.0, source: str = ""
) -> Path:
    """Write ``frames`` as a recording folder; every file is written atomically, the index last.

    Depth is stored as ``round(depth_m * depth_scale)`` in a 16-bit PNG: with the default 1000 (mm) a
    frame whose depth is whole millimetres (what an OAK gives) replays bit-identical; finer depth is
    rounded to 1 / ``depth_scale`` m.

    Raises:
        DatasetError: no frames, a bad ``depth_scale``, or depth beyond the 16-bit range at that scale.
    """
    from PIL import Image

    folder = Path(folder)
    if not frames:
        raise DatasetError(f"{folder}: no frames to record")
    if not np.isfinite(depth_scale) or depth_scale <= 0:
        raise DatasetError(f"{folder}: depth_scale must be positive (units per metre), got {depth_scale}")
    # Overwriting a recording: the new frames get names the old index does not list, and the index, written
    # last, switches from the old set to the new; an interrupted write leaves the old recording whole.
    old = _listed_frames(folder)
    prefix = next(p for p in ("frame", *(f"frame{k}" for k in range(1, len(old) + 2)))
                  if not any(n.startswith(f"{p}_") for n in old))
    names: list[str] = []
    try:
        for i, frame in enumerate(frames):
            name = f"{prefix}_{i:06d}"
            names.append(name)
            units = np.rint(frame.depth_mm.astype(np.float64) * (depth_scale / 1000.0))
            if units.max(initial=0) > _MAX_DEPTH_UNITS:
                raise DatasetError(
                    f"{folder}: frame {i} has depth {frame.depth_mm.max():.0f} mm, beyond 16 bits at depth_scale "
                    f"{depth_scale}; use a smaller depth_scale"
                )
            with atomic_path(folder / f"{name}.color.png") as tmp:
                Image.fromarray(np.ascontiguousarray(frame.color), mode="RGB").save(tmp, format="PNG")
            with atomic_path(folder / f"{name}.depth.png") as tmp:
                Image.fromarray(units.astype(np.uint16)).save(tmp, format="PNG")
            meta = {**frame.intrinsics.to_dict(), "pose": frame.pose.tolist(), "timestamp_s": frame.timestamp_s,
                    "name": frame.name}
            write_text(folder / f"{name}.json", json.dumps(meta, indent=1))
        index = {"format": FORMAT, "frames": names, "depth_scale": depth_scale, "source": source}
        write_text(folder / INDEX, json.dumps(index, indent=1))
    except BaseException:
        if _listed_frames(folder) != names:  # the new index is not in place: remove what this call wrote
            for name in names:
                for part in (".color.png", ".depth.png", ".json"):
                    (folder / f"{name}{part}").unlink(missing_ok=True)
        raise
    for file in folder.glob("frame*_*.*"):  # the replaced recording's frames, and those of interrupted writes
        stem = file.name.split(".", 1)[0]
        if re.fullmatch(r"frame\d*_\d{6}", stem) and stem not in names:
            file.unlink(missing_ok=True)
    log.info("%s: wrote %d frames", folder, len(frames))
    return folder
