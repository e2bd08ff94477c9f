"""Capture-like training objects: what a virtual OAK-D reconstructs of an object, as an object to touch in training.

A classifier trained on CAD meshes meets, on the robot, the camera's reconstruction of an object: surfaces
that ripple by tenths of a millimetre, a bottom closed against the table, insides (a mug's, a bowl's) that the
cameras barely see and that come back filled or shallow. Training on *virtual captures* of the training
instances shows the classifier those effects without ever showing it a test object:

- :func:`virtual_capture`: an object placed on a table, captured by a :class:`~perception.camera.VirtualOakCamera`
  from ``views`` orbit views, reconstructed by :func:`~perception.reconstruct.multiview.reconstruct_frames`
  (closed against the table, as ``visuotactile camera`` does) and brought to the training size with
  :func:`~perception.geometry.rescale`;
- :func:`catalogue_capture`: the same for a catalogue instance, a picklable loader for
  :class:`~tactile.dataset.objects.ObjectSpec`, so a :func:`~tactile.dataset.generate` worker reconstructs it;
- :func:`object_capture`: the same for any object a store can hold (a mesh file, say), set down on the table in a
  resting pose first;
- :func:`training_specs`: the objects of a training store: their CAD meshes, their captures, or both (``source``),
  captures named ``"<name>@capture"`` and marked as made from their object, so that splits by object keep the two
  together (``visuotactile generate --captures N``).

Units are millimetres; the same object, settings and seed give the same bytes.
"""

from __future__ import annotations

import functools
import hashlib
import time
from dataclasses import dataclass

import numpy as np

from perception.errors import InvalidArgumentError
from perception.geometry import DEFAULT_SIZE_MM, ObjectModel

#: Where the training objects come from (:func:`training_specs`).
SOURCES = ("cad", "capture", "both")
#: Suffix of a capture's object name.
CAPTURE_SUFFIX = "@capture"


@dataclass
class Capture:
    """What :func:`virtual_capture` made.

    Attributes:
        model: the reconstruction centred and scaled to ``size_mm`` (pose-free frame), named and labelled
            like the object.
        world: the reconstruction in the world frame at physical size (table top z = 0), mm.
        truth: the object as placed on the table (world frame), mm; compare ``world`` with it.
        seconds: capture and reconstruction wall time, s.
    """

    model: ObjectModel
    world: ObjectModel
    truth: ObjectModel
    seconds: float


#: Camera elevation of :func:`virtual_capture` above the table, degrees (the orbit of ``visuotactile camera``).
DEFAULT_ELEVATION_DEG = 35.0
#: What :func:`virtual_capture` passes on to :func:`~perception.reconstruct.multiview.reconstruct_frames`.
RECONSTRUCT_OPTIONS = ("method", "voxel_mm", "drop_flying")


def _check(views, distance_mm, size_mm, elevation_deg=DEFAULT_ELEVATION_DEG) -> None:
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or views < 1:
        raise InvalidArgumentError(f"virtual capture: views must be a positive integer, got {views!r}")
    for name, value in (("distance_mm", distance_mm), ("size_mm", size_mm)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not np.isfinite(value) \
                or value <= 0:
            raise InvalidArgumentError(f"virtual capture: {name} must be a positive number, got {value!r}")
    if isinstance(elevation_deg, bool) or not isinstance(elevation_deg, (int, float, np.number)) \
            or not 0 < elevation_deg < 90:
        raise InvalidArgumentError(
            f"virtual capture: elevation_deg must be a number in (0, 90) degrees, got {elevation_deg!r}")


def virtual_capture(
    model: ObjectModel,
    *,
    views: int = 4,
    distance_mm: float = 500.0,
    size_mm: float = DEFAULT_SIZE_MM,
    seed: int = 0,
    name: str | None = None,
    elevation_deg: float = DEFAULT_ELEVATION_DEG,
    reconstruct: dict | None = None,
) -> Capture:
    """``model`` standing upright on a table, captured by a virtual OAK-D from ``views`` views evenly spaced in
    azimuth at ``distance_mm`` (``elevation_deg`` above the table, 35 degrees by default; stereo noise seeded by
    ``seed``), reconstructed closed against the table and rescaled to ``size_mm`` (the enclosing-sphere diameter
    of the pose-free frame).

    Args:
        model: the object (mm), in the pose it stands on the table in (+z up).
        views, distance_mm, elevation_deg: the orbit of the camera (a robot's camera looking down at a table
            sees it from 30 to 80 degrees; the GraspNet RealSense from about 57 to 79).
        size_mm: the size the reconstruction is brought to (that of the training objects).
        seed: seeds the stereo noise and the reconstruction (RANSAC).
        name: the reconstruction's name (default ``"<model name>@capture"``).
        reconstruct: settings of :func:`~perception.reconstruct.multiview.reconstruct_frames` among
            :data:`RECONSTRUCT_OPTIONS` (e.g. those ``fusion.camera.reconstruct_capture`` uses on real frames:
            ``{"method": "convex", "voxel_mm": 3.0, "drop_flying": True}``); default: its defaults.

    Raises:
        InvalidArgumentError: views not a positive integer, a non-positive distance or size, an elevation
            outside (0, 90) degrees, or an unknown reconstruction setting.
        InvalidMeshError: the frames hold no object that can be reconstructed.
    """
    from perception.camera import VirtualOakCamera
    from perception.geometry import rescale
    from perception.reconstruct.multiview import reconstruct_frames
    from perception.reconstruct.tabletop import check_voxel

    _check(views, distance_mm, size_mm, elevation_deg)
    options = dict(reconstruct or {})
    unknown = sorted(set(options) - set(RECONSTRUCT_OPTIONS))
    if unknown:
        raise InvalidArgumentError(f"virtual capture: unknown reconstruction settings {unknown}; "
                                   f"choose among {', '.join(RECONSTRUCT_OPTIONS)}")
    name = name or f"{model.name}{CAPTURE_SUFFIX}"
    if "voxel_mm" in options:  # before the views are rendered (about 0.5 s each), not after
        check_voxel(options["voxel_mm"], f"virtual capture of {model.name}")
    start = time.perf_counter()
    camera = VirtualOakCamera(model, seed=int(seed))
    rec = reconstruct_frames(camera.capture_views(int(views), float(distance_mm), float(elevation_deg)),
                             target=camera.target, name=name, label=model.label, seed=int(seed), **options)
    seconds = time.perf_counter() - start
    scaled = rescale(rec.model, float(size_mm), name=name)
    return Capture(scaled, rec.model, camera.truth, seconds)


def resting_rotation(model: ObjectModel, seed: int | np.random.Generator) -> np.ndarray:
    """(3, 3) rotation that sets ``model`` down on a table (+z up) in a stable resting pose, as an object dropped
    gently in a random orientation comes to rest: its convex hull lands on the face the ray from its centre of
    mass along a uniformly random direction meets, and rolls over an edge while the centre of mass lies
    outside the face (quasi-static toppling), until it lies on a face that holds it; then a uniformly random turn
    about the vertical. A box lies on a face (never on a corner, as a random rotation leaves it), a can on its
    side or its end, with the probabilities of the drop. The centre of mass is the area-weighted surface
    centroid (:attr:`~perception.geometry.ObjectModel.center`, about which :func:`~perception.geometry.rotate`
    turns). Same seed, same bytes.

    Raises:
        InvalidMeshError: the model's vertices span no volume (a flat or degenerate mesh has no resting face).
    """
    from scipy.spatial import ConvexHull, QhullError
    from scipy.spatial.transform import Rotation

    from perception.errors import InvalidMeshError

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    centre = model.center
    try:
        hull = ConvexHull(model.vertices - centre)
    except (QhullError, ValueError) as exc:
        raise InvalidMeshError(f"{model.name}: no resting pose, the vertices span no volume ({exc})") from None
    normals, offsets = hull.equations[:, :3], -hull.equations[:, 3]  # n . x = offset on each face, offset > 0
    points, faces = hull.points, hull.simplices
    down = rng.normal(size=3)
    down /= np.linalg.norm(down)
    reach = normals @ down
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(reach > 0, offsets / reach, np.inf)
    face = int(np.argmin(t))  # the face the drop direction meets
    for _ in range(4 * len(faces)):  # each roll lowers the centre of mass or walks across one flat face
        a, b, c = points[faces[face]]
        foot = offsets[face] * normals[face]  # the centre of mass projected onto the face's plane
        w = np.linalg.lstsq(np.stack([b - a, c - a], axis=1), foot - a, rcond=None)[0]
        bary = np.array([1.0 - w.sum(), w[0], w[1]])
        if bary.min() >= -1e-9:
            break
        face = int(hull.neighbors[face][int(np.argmin(bary))])  # over the edge opposite the most negative vertex
    turn = Rotation.from_rotvec([0.0, 0.0, rng.uniform(0.0, 2.0 * np.pi)])
    align, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [normals[face]])
    return (turn * align).as_matrix()


def _vertical_turn(turn_deg, where: str) -> np.ndarray:
    """(3, 3) rotation by ``turn_deg`` degrees about +z (the table's vertical).

    Raises:
        InvalidArgumentError: a turn that is not a finite number (``where`` names the caller).
    """
    if isinstance(turn_deg, bool) or not isinstance(turn_deg, (int, float, np.number)) or not np.isfinite(turn_deg):
        raise InvalidArgumentError(f"{where}: turn_deg must be a finite number, got {turn_deg!r}")
    a = np.radians(float(turn_deg))
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def catalogue_capture(
    class_name: str, seed: int, *, views: int = 4, distance_mm: float = 500.0, size_mm: float = DEFAULT_SIZE_MM,
    turn_deg: float = 0.0, camera_seed: int | None = None,
) -> ObjectModel:
    """The virtual capture (:func:`virtual_capture`) of catalogue instance ``(class_name, seed)`` at ``size_mm``,
    turned by ``turn_deg`` about the vertical axis (through its centre) before it is set on the table (the
    cameras see it from other sides), camera seeded by ``camera_seed`` (default ``seed``): a loader for
    :class:`~tactile.dataset.objects.ObjectSpec`.

    Raises:
        DatasetError: unknown class or bad seed (from :func:`perception.shapes.make_object`).
        InvalidArgumentError, InvalidMeshError: as :func:`virtual_capture`, or a turn that is not finite.
    """
    from perception.geometry import rotate
    from perception.shapes import make_object

    _check(views, distance_mm, size_mm)
    turn = _vertical_turn(turn_deg, "catalogue_capture")
    model = make_object(class_name, seed)
    if turn_deg:
        model = rotate(model, turn)
    camera_seed = seed if camera_seed is None else camera_seed
    return virtual_capture(model, views=views, distance_mm=distance_mm, size_mm=size_mm, seed=camera_seed).model


def _capture_seed(name: str) -> int:
    """A camera seed for the object named ``name`` (Open3D takes 31 bits): the same name, the same seed."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little") % 2**31


def object_capture(spec, *, views: int = 4, distance_mm: float = 500.0, size_mm: float = DEFAULT_SIZE_MM,
                   turn_deg: float = 0.0, camera_seed: int | None = None) -> ObjectModel:
    """The virtual capture (:func:`virtual_capture`) of the object of ``spec`` (an
    :class:`~tactile.dataset.objects.ObjectSpec`: a mesh file, say) at ``size_mm``: loaded, set down on the table in
    the resting pose :func:`resting_rotation` draws from the camera seed (a stored mesh's pose says nothing of how it
    stands), turned by ``turn_deg`` about the vertical, captured with the camera seeded by ``camera_seed`` (default:
    from the object's name). A loader for :class:`~tactile.dataset.objects.ObjectSpec`.

    Raises:
        InvalidArgumentError: bad capture settings or a turn that is not finite.
        InvalidMeshError: a flat object (no resting pose) or frames that hold no object; and what loading raises.
    """
    from perception.geometry import rotate

    _check(views, distance_mm, size_mm)
    turn = _vertical_turn(turn_deg, "object_capture")
    camera_seed = _capture_seed(spec.name) if camera_seed is None else int(camera_seed)
    model = spec.load()
    model = rotate(model, turn @ resting_rotation(model, camera_seed))
    return virtual_capture(model, views=views, distance_mm=distance_mm, size_mm=size_mm, seed=camera_seed).model


def capture_name(name: str, index: int = 0) -> str:
    """The object name of capture ``index`` of the object named ``name``: ``"<name>@capture"`` for the first,
    ``"<name>@capture<index>"`` for the others."""
    return f"{name}{CAPTURE_SUFFIX}{index or ''}"


def is_capture(name: str) -> bool:
    """Whether an object name (of a store made by :func:`training_specs`) is a capture's."""
    _, sep, tail = str(name).rpartition(CAPTURE_SUFFIX)
    return bool(sep) and (tail == "" or tail.isdigit())


#: Camera seed step between the captures of one object (:func:`training_specs`).
_CAMERA_SEED_STEP = 100_003


def training_specs(objects, source: str = "both", *, views: int = 4, distance_mm: float = 500.0,
                   size_mm: float = DEFAULT_SIZE_MM, captures_per_object: int = 1) -> list:
    """The :class:`~tactile.dataset.objects.ObjectSpec` of a training store made of ``objects`` (anything
    :func:`~tactile.dataset.generate` takes: catalogue (class, seed) pairs, (path, label) pairs, a class-per-folder
    collection, specs): their CAD meshes (``"cad"``, named as :func:`~tactile.dataset.generate` names them), their
    virtual captures (``"capture"``, reconstructed in the worker) or both, CAD first (``"both"``). A capture is
    marked as made from its object (``made_from``), so splits by object keep them on one side.

    A catalogue object is captured standing as it is built (:func:`catalogue_capture`, the camera seeded by its
    seed), any other in a resting pose (:func:`object_capture`, the camera seeded by its name). ``captures_per_object``
    captures of each object: capture k (named by :func:`capture_name`) turns the object by
    k * 360 / (views * captures_per_object) degrees about the vertical axis, so the captures look at it from azimuths
    between the views, and steps the camera seed by 100003 k.

    Raises:
        InvalidArgumentError: unknown ``source`` or bad capture settings.
        DatasetError: what :func:`~tactile.dataset.objects.object_specs` refuses (an unknown class, a negative seed,
            an item of no known form, two objects of one name).
    """
    from tactile.dataset.objects import ObjectSpec, object_specs

    if source not in SOURCES:
        raise InvalidArgumentError(f"training_specs: unknown source {source!r}; choose one of {', '.join(SOURCES)}")
    _check(views, distance_mm, size_mm)
    n = captures_per_object
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InvalidArgumentError(f"training_specs: captures_per_object must be a positive integer, got {n!r}")
    cad = object_specs(objects)
    if source == "cad":
        return cad
    captures = []
    for spec in cad:
        if spec.made_from is not None or is_capture(spec.name):
            raise InvalidArgumentError(f"training_specs: {spec.name!r} is made from another object already; give the "
                                       "objects themselves")
        base = spec.catalogue[1] if spec.catalogue is not None else _capture_seed(spec.name)
        for k in range(int(n)):
            settings = {"views": int(views), "distance_mm": float(distance_mm), "size_mm": float(size_mm)}
            if k:
                settings.update(turn_deg=k * 360.0 / (int(views) * int(n)),
                                camera_seed=(base + _CAMERA_SEED_STEP * k) % 2**31)
            loader = (functools.partial(catalogue_capture, *spec.catalogue, **settings) if spec.catalogue is not None
                      and spec.rotation_seed is None else functools.partial(object_capture, spec, **settings))
            captures.append(ObjectSpec(capture_name(spec.name, k), spec.label, loader=loader, made_from=spec))
    return captures if source == "capture" else cad + captures


__all__ = [
    "CAPTURE_SUFFIX", "DEFAULT_ELEVATION_DEG", "RECONSTRUCT_OPTIONS", "SOURCES", "Capture", "capture_name",
    "catalogue_capture", "is_capture", "object_capture", "resting_rotation", "training_specs", "virtual_capture",
]
