"""Exploring an object by touch: press the FSR pad at every probe of a contour, giving a tactile sequence."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perception.geometry import ObjectModel
from tactile.contours import Contour, Plane
from tactile.sensor import FSRSensor


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
    return TactileSequence(
        frames=frames,
        normals=contour.normals.copy(),
        positions=contour.positions.copy(),
        tangents=contour.tangents.copy(),
        pad_sides_mm=sides,
        plane=contour.plane,
        object_name=model.name,
        label=model.label,
        strategy=strategy,
        seed=int(seed) if isinstance(seed, (int, np.integer)) else None,
    )


__all__ = ["TactileSequence", "explore"]
