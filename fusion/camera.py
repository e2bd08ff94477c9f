"""Recognizing an object from an RGB-D capture (virtual OAK, live OAK or a recording): what ``visuotactile camera``
runs (:func:`recognize_capture`).

capture -> table removed, object segmented, views fused -> surface (Poisson), closed where no camera saw it
(the bottom on the table) from the carved space -> scaled like the training objects (150 mm diagonal) ->
contours -> virtual FSR sequences -> classifier (``--model``) -> touches fused -> class.
Without ``--model`` everything up to the tactile sequences runs and is reported. Every object segmented in
the first view is listed (centre and size in mm, pixel centroid); ``--target U,V`` touches the one that pixel
of the first view shows (default: the object in front, on the optical axis). A figure (capture, cloud,
reconstructed mesh with the explored contours) and ``summary.json`` go to ``--out``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from perception.errors import DatasetError, InvalidArgumentError

log = logging.getLogger(__name__)


def _virtual(source: str, views: int, distance_mm: float, seed: int):
    from perception.camera import VirtualOakCamera
    from perception.shapes import make_object

    spec = source.split(":", 1)[1]
    class_name, _, instance = spec.partition("/")
    if instance and not instance.isdigit():
        raise DatasetError(f"--source {source}: expected virtual:<class> or virtual:<class>/<seed>")
    model = make_object(class_name, int(instance) if instance else seed)
    camera = VirtualOakCamera(model, seed=seed)
    return camera.capture_views(views, distance_mm), camera.truth, camera.target, class_name


def _oak(views: int):
    from perception.camera import OakCamera, find_oak_devices
    from perception.camera.oak import NO_DEVICE_HINT
    from perception.errors import DeviceNotFoundError

    if not find_oak_devices():  # answers at once; opening a pipeline with no device would wait ~11 s
        raise DeviceNotFoundError(f"no OAK device found; {NO_DEVICE_HINT}")
    with OakCamera() as camera:
        for _ in range(10):  # let auto-exposure settle
            camera.capture()
        # One static camera gives one viewpoint; more views need known poses (robot, turntable).
        return [camera.capture()], None, None, None


def acquire(source: str, views: int = 4, distance_mm: float = 500.0, seed: int = 0):
    """Frames, true mesh (virtual only), target point (mm) and true class of ``source``.

    Raises:
        DatasetError: an unknown source or unreadable recording.
        DeviceNotFoundError: ``oak`` with no device connected.
    """
    from perception.camera import is_recording, read_recording

    if views < 1:
        raise InvalidArgumentError(f"--views must be >= 1, got {views}")
    if source.startswith("virtual:"):
        return _virtual(source, views, distance_mm, seed)
    if source == "oak":
        return _oak(views)
    folder = Path(source)
    if not folder.is_dir() or not is_recording(folder):
        raise DatasetError(
            f"--source {source}: not virtual:<class>, oak, or a recording folder "
            "(recording.json, or color.png + depth.png + camera.json)"
        )
    frames = read_recording(folder)
    return frames, None, None, None


def _optical_axis_target(frame) -> np.ndarray:
    """The point on the first camera's optical axis at the median depth (pick the object in front)."""
    z = float(np.median(frame.depth_mm[frame.valid])) if frame.valid.any() else 500.0
    return frame.pose[:3, :3] @ np.array([0.0, 0.0, z]) + frame.pose[:3, 3]


def _figure(frames, rec, model, contours, path: Path) -> Path:
    from matplotlib.figure import Figure

    from perception.atomic import save_figure
    from perception.render import render_views

    fig = Figure(figsize=(13, 3.6))
    axes = fig.subplots(1, 4)
    axes[0].imshow(frames[0].color)
    axes[0].set_title(f"capture ({len(frames)} view{'s' if len(frames) > 1 else ''})")
    scene, first = rec.scenes[0], frames[0]
    k = first.intrinsics

    def to_image(points):  # world mm -> first camera's pixels (column, row)
        cam = (points - first.pose[:3, 3]) @ first.pose[:3, :3]
        z = np.where(cam[:, 2] > 0, cam[:, 2], np.nan)
        return k.fx * cam[:, 0] / z + k.cx, k.fy * cam[:, 1] / z + k.cy

    labels = scene.labels
    for mask, color in ((labels == -2, "0.8"), (labels == -1, "0.93")):
        axes[1].scatter(*to_image(scene.points[mask]), s=0.1, c=color, rasterized=True)
    objects = labels >= 0
    axes[1].scatter(*to_image(scene.points[objects]), s=0.2, c=labels[objects] % 20, cmap="tab20", vmin=0, vmax=19,
                    rasterized=True)
    centers = np.array([c.center for c in scene.clusters]).reshape(-1, 3)
    axes[1].plot(*to_image(centers), "k+", ms=8)
    axes[1].set_title(f"view 0: table + {len(scene.clusters)} objects")
    if len(rec.support):  # where the surface is closed unseen (the bottom on the table), under the seen points
        axes[2].scatter(*to_image(rec.support), s=0.3, c="0.75", rasterized=True)
    u, v = to_image(rec.points)
    axes[2].scatter(u, v, s=0.3, c=rec.points @ first.pose[:3, 2], cmap="viridis", rasterized=True)
    axes[2].set_title(f"fused object cloud ({len(rec.points)} points, {len(rec.support)} unseen)")
    axes[1].set_xlim(0, k.width)
    axes[1].set_ylim(k.height, 0)
    pad = 0.1 * max(np.nanmax(u) - np.nanmin(u), np.nanmax(v) - np.nanmin(v), 1.0)
    axes[2].set_xlim(np.nanmin(u) - pad, np.nanmax(u) + pad)
    axes[2].set_ylim(np.nanmax(v) + pad, np.nanmin(v) - pad)
    for ax in axes[1:3]:
        ax.set_aspect("equal")
    view = render_views(model, 1, 256, 256, directions=np.array([[0.3, -1.0, 0.6]]))[0]
    axes[3].imshow(view.intensity, cmap="gray")
    for contour in contours:
        uv = view.camera.project(contour.positions)
        axes[3].plot(uv[:, 0], uv[:, 1], ".-", ms=2, lw=0.8)
    axes[3].set_title(f"reconstruction, {len(contours)} contours")
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


#: Reconstruction settings (:func:`perception.reconstruct.multiview.reconstruct_frames`) by kind of camera, see
#: :func:`reconstruct_capture`.
REAL_RECONSTRUCTION = {"method": "convex", "voxel_mm": 3.0, "drop_flying": True}
VIRTUAL_RECONSTRUCTION = {"method": "euclidean", "voxel_mm": 2.0, "drop_flying": False}


def reconstruct_capture(frames, *, virtual: bool, target=None, target_pixel=None, name: str = "capture",
                        seed: int = 0):
    """The picked object of a capture reconstructed with the settings its kind of camera needs
    (:func:`perception.reconstruct.multiview.reconstruct_frames`, world mm): on real frames the convex
    segmentation tells touching objects apart, which needs 3 mm voxels on real depth noise; virtual frames use
    the plain Euclidean clusters at 2 mm. Real frames lose their flying pixels at depth edges first
    (:func:`perception.reconstruct.tabletop.flying_pixels`): kept, they joined the GraspNet cracker box to the
    robot base behind it (522 mm) and made the soup can 175 mm across (122 mm true)."""
    from perception.reconstruct.multiview import reconstruct_frames

    settings = VIRTUAL_RECONSTRUCTION if virtual else REAL_RECONSTRUCTION
    return reconstruct_frames(frames, target=target, target_pixel=target_pixel, name=name, seed=seed, **settings)


def recognize_capture(
    source: str,
    *,
    views: int = 4,
    distance_mm: float = 500.0,
    model_path: str | None = None,
    contours: int = 8,
    strategy: str = "blind",
    seed: int = 0,
    out: str | Path | None = None,
    target_pixel: tuple[float, float] | None = None,
    trust_pickle: bool = False,
) -> dict:
    """The whole camera path; returns the summary (see the module docstring). ``target_pixel``: (column, row)
    of the object to touch in the first frame.

    Raises:
        VisuotactileError subclasses: bad source, no device, no object, unreadable model.

    Examples:
        >>> summary = recognize_capture("virtual:box/1", views=2, contours=2)  # no model: up to the touches
        >>> summary["true_class"], summary["sequences"], summary["prediction"]
        ('box', 2, None)
    """
    timings = {}
    start = time.perf_counter()
    frames, truth, target, true_class = acquire(source, views, distance_mm, seed)
    timings["capture_s"] = time.perf_counter() - start
    # Only now the geometry stack: without a device the user hears so before Open3D has loaded.
    from perception.geometry import DEFAULT_SIZE_MM, rescale
    from perception.reconstruct.surface import surface_error
    from perception.reconstruct.tabletop import describe_objects
    from tactile.contours import make_contour
    from tactile.explore import SequenceBatch
    from tactile.sensor import FSRSensor
    from tactile.touching import touch
    virtual = truth is not None
    start = time.perf_counter()
    if target_pixel is None and target is None:
        target = _optical_axis_target(frames[0])
    rec = reconstruct_capture(frames, virtual=virtual, target=target, target_pixel=target_pixel, name=f"{source}",
                              seed=seed)
    timings["reconstruct_s"] = time.perf_counter() - start
    summary: dict = {
        "source": source,
        "frames": len(frames),
        "objects_in_first_view": len(rec.scenes[0].clusters),
        "objects": describe_objects(rec.scenes[0], frames[0]),
        "picked": {
            "index": rec.picked,
            "size_mm": [round(float(x), 1) for x in rec.object.size_mm],
            "diagonal_mm": round(rec.object.diagonal_mm, 1),
            "center_mm": [round(float(x), 1) for x in rec.object.center],
        },
        "warnings": list(rec.warnings),
        "object_points": len(rec.points),
        "reconstruction": {
            "vertices": rec.model.n_vertices,
            "triangles": rec.model.n_triangles,
            "diagonal_mm": rec.model.diagonal,
            "watertight": rec.model.is_watertight,
            "unseen_points": len(rec.support),  # added where no camera saw the surface (the carved space)
        },
    }
    if virtual:
        summary["true_class"] = true_class
        summary["reconstruction"]["error_mm"] = surface_error(rec.model, truth)
    clf = None
    if model_path is not None:
        from fusion.base import load_model

        clf = load_model(model_path, trust_pickle=trust_pickle)
    sensor = clf.sensor() if clf is not None else None
    probes = clf.probes if clf is not None else 25
    # Touch the object at the size the classifiers were trained at (catalogue and loaders: 150 mm, pose-free).
    obj = rescale(rec.model, DEFAULT_SIZE_MM)
    start = time.perf_counter()
    sequences = touch(obj, strategy, contours, sensor, probes, seed)
    timings["touch_s"] = time.perf_counter() - start
    class_names = [str(c) for c in clf.classes_] if clf is not None else None
    spec = (sensor if sensor is not None else FSRSensor()).spec()
    batch = SequenceBatch.from_sequences(sequences, class_names=class_names, sensor_spec=spec)
    summary["sequences"] = len(batch)
    summary["probes"] = batch.n_probes
    summary["prediction"] = None
    if clf is not None:
        from fusion.openset import answer

        start = time.perf_counter()
        decision = answer(clf, batch)
        fused = decision["fused"]
        open_set = {} if decision["known_score"] is None else {
            "unknown": decision["unknown"], "closest": class_names[int(np.argmax(fused))],
            "known_score": decision["known_score"], "threshold": decision["threshold"]}
        timings["classify_s"] = time.perf_counter() - start
        order = np.argsort(-fused)
        summary["prediction"] = {
            "class": "unknown" if open_set.get("unknown") else class_names[int(order[0])],
            "probabilities": {class_names[int(i)]: float(fused[i]) for i in order},
            **open_set,
        }
    summary["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
    if out is not None:
        import json

        from perception.atomic import write_text

        out = Path(out)
        figure_contours = [make_contour(obj, s.plane, probes) for s in sequences]
        summary["figure"] = str(_figure(frames, rec, obj, figure_contours, out / "camera.png"))
        write_text(out / "summary.json", json.dumps(summary, indent=2, default=str, allow_nan=False))
    return summary


__all__ = ["REAL_RECONSTRUCTION", "VIRTUAL_RECONSTRUCTION", "acquire", "recognize_capture", "reconstruct_capture"]
