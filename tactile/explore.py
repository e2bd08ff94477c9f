"""Exploring an object by touch: press the FSR pad at every probe of a contour, giving a tactile sequence."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from perception.errors import DatasetError
from perception.geometry import ObjectModel
from tactile.contours import Contour, Plane
from tactile.sensor import FSRSensor


def sequence_nbytes(probes: int, rows: int, cols: int, taxel_bytes: int = 4) -> int:
    """Bytes of one tactile sequence in memory: ``taxel_bytes`` per taxel of each frame (float32 frames: 4) and the
    ten float32 pose values of each probe (normal, position and tangent, 3 each, and the pad side)."""
    return int(probes) * (int(rows) * int(cols) * int(taxel_bytes) + 4 * 10)


@dataclass(eq=False)
class TactileSequence:
    """What one contour exploration records.

    Attributes:
        frames: (N, rows, cols) float32 cutaneous images (mm in gap mode, pressure in contact mode).
        normals: (N, 3) unit outward surface normals at the probes (the kinesthetic cue).
        positions: (N, 3) probe positions, mm.
        tangents: (N, 3) unit pad x axes (along the contour).
        pad_sides_mm: (N,) pad side used at each probe after adaptive shrinking, mm.
        plane: the cutting plane of the contour.
        object_name: the explored object's name.
        label: its class, if known.
        strategy: how the contour was chosen ("manual", "blind", "guided", ...).
        seed: the integer seed of the sensor noise, if one was given.
    """

    frames: np.ndarray
    normals: np.ndarray
    positions: np.ndarray
    tangents: np.ndarray
    pad_sides_mm: np.ndarray
    plane: Plane
    object_name: str
    label: str | None = None
    strategy: str = "manual"
    seed: int | None = None

    @classmethod
    def of_contour(cls, model: ObjectModel, contour: Contour, frames: np.ndarray, sides: np.ndarray, *,
                   seed=None, strategy: str = "manual") -> TactileSequence:
        """The sequence of ``contour`` on ``model`` read as ``frames`` with pads of ``sides``: it records the
        contour's (planned) poses, copied, and the seed when it is an integer."""
        return cls(frames=frames, normals=contour.normals.copy(), positions=contour.positions.copy(),
                   tangents=contour.tangents.copy(), pad_sides_mm=sides, plane=contour.plane, object_name=model.name,
                   label=model.label, strategy=strategy,
                   seed=int(seed) if isinstance(seed, (int, np.integer)) else None)

    @property
    def n_probes(self) -> int:
        return len(self.frames)


def explore(
    model: ObjectModel,
    contour: Contour,
    sensor: FSRSensor | None = None,
    *,
    seed: int | np.random.Generator | None = None,
    adaptive: bool = True,
    strategy: str = "manual",
) -> TactileSequence:
    """Press ``sensor`` (default :class:`FSRSensor`) at every probe of ``contour`` on ``model``.

    Raises:
        SensorSpecError: the contour has no probes.
    """
    sensor = sensor or FSRSensor()
    frames, sides = sensor.press(
        model, contour.positions, contour.normals, contour.tangents, seed=seed, adaptive=adaptive
    )
    return TactileSequence.of_contour(model, contour, frames, sides, seed=seed, strategy=strategy)


@dataclass(eq=False)
class SequenceBatch:
    """S tactile sequences of P probes each, stacked: what a dataset store holds and a classifier takes.

    The contract between :mod:`tactile.dataset` (which writes and reads it) and :mod:`fusion` (which learns
    from it). Arrays are in the object's frame, mm.

    Attributes:
        frames: (S, P, rows, cols) float32 cutaneous images (mm in gap mode).
        normals: (S, P, 3) float32 unit outward normals at the probes (the paper's kinesthetic cue).
        positions: (S, P, 3) float32 probe positions, mm.
        tangents: (S, P, 3) float32 unit pad x axes (along the contour).
        pad_sides_mm: (S, P) float32 pad side after adaptive shrinking, mm.
        plane_points: (S, 3) float64 a point of each contour plane (the object centre), mm.
        plane_normals: (S, 3) float64 unit normal of each contour plane.
        labels: (S,) int64 class index into ``class_names``, -1 where unknown.
        object_ids: (S,) int64 which object each sequence touched (index into ``object_names``).
        class_names: the class list the labels index.
        object_names: the object list the object ids index.
        sensor_spec: :meth:`FSRSensor.spec` of the sensor that recorded the frames.
    """

    frames: np.ndarray
    normals: np.ndarray
    positions: np.ndarray
    tangents: np.ndarray
    pad_sides_mm: np.ndarray
    plane_points: np.ndarray
    plane_normals: np.ndarray
    labels: np.ndarray
    object_ids: np.ndarray
    class_names: tuple[str, ...] = ()
    object_names: tuple[str, ...] = ()
    sensor_spec: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.class_names = tuple(self.class_names)
        self.object_names = tuple(self.object_names)
        if self.frames.ndim != 4:
            raise DatasetError(f"SequenceBatch: frames must be (S, P, rows, cols), got shape {self.frames.shape}")
        s, p = self.frames.shape[:2]
        expected = {
            "normals": (s, p, 3), "positions": (s, p, 3), "tangents": (s, p, 3), "pad_sides_mm": (s, p),
            "plane_points": (s, 3), "plane_normals": (s, 3), "labels": (s,), "object_ids": (s,),
        }
        for name, shape in expected.items():
            if np.shape(getattr(self, name)) != shape:
                raise DatasetError(
                    f"SequenceBatch: {name} must have shape {shape} to match frames {self.frames.shape}, "
                    f"got {np.shape(getattr(self, name))}"
                )

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def n_probes(self) -> int:
        return self.frames.shape[1]

    @property
    def grid(self) -> tuple[int, int]:
        """Taxel (rows, cols)."""
        return self.frames.shape[2], self.frames.shape[3]

    def subset(self, index) -> SequenceBatch:
        """The sequences at ``index`` (an index array, a boolean mask or a slice), same class/object lists."""
        pick = lambda a: np.asarray(a)[index]
        return SequenceBatch(
            frames=pick(self.frames), normals=pick(self.normals), positions=pick(self.positions),
            tangents=pick(self.tangents), pad_sides_mm=pick(self.pad_sides_mm),
            plane_points=pick(self.plane_points), plane_normals=pick(self.plane_normals),
            labels=pick(self.labels), object_ids=pick(self.object_ids), class_names=self.class_names,
            object_names=self.object_names, sensor_spec=dict(self.sensor_spec),
        )

    @classmethod
    def from_sequences(
        cls,
        sequences: Sequence[TactileSequence],
        class_names: Sequence[str] | None = None,
        sensor_spec: dict | None = None,
    ) -> SequenceBatch:
        """Stack explored sequences (same probe count and taxel grid). Labels index ``class_names``
        (default: the sorted labels present); objects are numbered in order of first appearance.

        Raises:
            DatasetError: no sequences, mixed shapes, or a label not in ``class_names``.
        """
        if not sequences:
            raise DatasetError("SequenceBatch.from_sequences: no sequences given")
        shapes = {s.frames.shape for s in sequences}
        if len(shapes) != 1:
            raise DatasetError(f"SequenceBatch.from_sequences: sequences differ in shape: {sorted(shapes)}")
        if class_names is None:
            class_names = sorted({s.label for s in sequences if s.label is not None})
        class_index = {name: i for i, name in enumerate(class_names)}
        unknown = {s.label for s in sequences if s.label is not None and s.label not in class_index}
        if unknown:
            raise DatasetError(f"SequenceBatch.from_sequences: labels {sorted(unknown)} not in {list(class_names)}")
        object_names = list(dict.fromkeys(s.object_name for s in sequences))
        object_index = {name: i for i, name in enumerate(object_names)}
        stack = lambda attr, dtype: np.stack([getattr(s, attr) for s in sequences]).astype(dtype)
        return cls(
            frames=stack("frames", np.float32),
            normals=stack("normals", np.float32),
            positions=stack("positions", np.float32),
            tangents=stack("tangents", np.float32),
            pad_sides_mm=stack("pad_sides_mm", np.float32),
            plane_points=np.stack([s.plane.point for s in sequences]).astype(np.float64),
            plane_normals=np.stack([s.plane.normal for s in sequences]).astype(np.float64),
            labels=np.array([class_index.get(s.label, -1) for s in sequences], dtype=np.int64),
            object_ids=np.array([object_index[s.object_name] for s in sequences], dtype=np.int64),
            class_names=tuple(class_names),
            object_names=tuple(object_names),
            sensor_spec=dict(sensor_spec or {}),
        )

    @classmethod
    def concatenate(cls, batches: Sequence[SequenceBatch]) -> SequenceBatch:
        """The sequences of ``batches`` in order, as one batch. They must share the class list, the sensor spec and
        the sequence shape; object lists are joined (an object named in several batches keeps one id).

        Raises:
            DatasetError: no batches, something that is not a batch, object ids outside a batch's object list, or
                batches that differ in classes, sensor or shape.
        """
        if not isinstance(batches, (list, tuple)):
            raise DatasetError(f"SequenceBatch.concatenate: give a list of batches, got a {type(batches).__name__}")
        if not batches:
            raise DatasetError("SequenceBatch.concatenate: no batches given")
        for k, b in enumerate(batches):
            if not isinstance(b, SequenceBatch):
                raise DatasetError(f"SequenceBatch.concatenate: item {k} is a {type(b).__name__}, not a SequenceBatch")
            if len(b) and not (0 <= b.object_ids.min() and b.object_ids.max() < len(b.object_names)):
                raise DatasetError(f"SequenceBatch.concatenate: batch {k} has object ids outside its "
                                   f"{len(b.object_names)} object names")
        first = batches[0]
        for k, b in enumerate(batches[1:], 1):
            if b.class_names != first.class_names:
                raise DatasetError(f"SequenceBatch.concatenate: batch {k} has classes {list(b.class_names)}, "
                                   f"batch 0 {list(first.class_names)}")
            if b.sensor_spec != first.sensor_spec:
                raise DatasetError(f"SequenceBatch.concatenate: batch {k} was recorded by another sensor")
            if b.frames.shape[1:] != first.frames.shape[1:]:
                raise DatasetError(f"SequenceBatch.concatenate: batch {k} has sequences of shape {b.frames.shape[1:]}, "
                                   f"batch 0 {first.frames.shape[1:]}")
        names = list(dict.fromkeys(n for b in batches for n in b.object_names))
        index = {n: i for i, n in enumerate(names)}
        ids = [np.array([index[n] for n in b.object_names], dtype=np.int64)[b.object_ids] for b in batches]
        # In the first batch's dtypes (the contract's: float32 frames), so a float64 batch does not double the memory.
        join = lambda attr: np.concatenate([getattr(b, attr) for b in batches]).astype(getattr(first, attr).dtype,
                                                                                         copy=False)
        return cls(frames=join("frames"), normals=join("normals"), positions=join("positions"),
                   tangents=join("tangents"), pad_sides_mm=join("pad_sides_mm"), plane_points=join("plane_points"),
                   plane_normals=join("plane_normals"), labels=join("labels"), object_ids=np.concatenate(ids),
                   class_names=first.class_names, object_names=tuple(names), sensor_spec=dict(first.sensor_spec))


__all__ = ["SequenceBatch", "TactileSequence", "explore", "sequence_nbytes"]
