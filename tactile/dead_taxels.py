"""Dead taxels: find them in a tactile sequence and fill them in from their neighbours.

A dead FSR taxel reads "nothing" (the sensing range in gap mode, zero pressure in contact mode) whatever
touches it, in every frame. Within one sequence (one contour, one press) the pad slides over the surface, so a
live taxel reading nothing at every probe while its neighbours feel the surface is implausible; a region that
really reads nothing (the pad hanging over the object's edge) is a block of such taxels, not an isolated one.
So a taxel counts as dead when it reads the dead value in every frame of its sequence and at most
``max_dead_neighbours`` of its 8 neighbours do too. It is then replaced, frame by frame, by the mean of its
live neighbours: exact on surfaces that are linear across a taxel's neighbourhood (a plane), close on smooth ones.

Classifiers trained on clean frames read a dead taxel as a spike of the full range (contourlet and wavelet
features see it as a strong edge); repairing the frames first needs no retraining and no dead-taxel map.
"""

from __future__ import annotations

import numpy as np

from perception.errors import SensorSpecError
from tactile.sensor import FSRSensor

#: The 8-neighbourhood as (row, col) offsets.
NEIGHBOURS = tuple((dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0))


def _neighbour_sum(values: np.ndarray) -> np.ndarray:
    """Sum over the in-bounds 8-neighbours of each taxel of (..., R, C) ``values`` (zero padding)."""
    rows, cols = values.shape[-2:]
    padded = np.pad(values, [(0, 0)] * (values.ndim - 2) + [(1, 1), (1, 1)])
    total = np.zeros(values.shape, dtype=np.result_type(values.dtype, np.float64))
    for dr, dc in NEIGHBOURS:
        total += padded[..., 1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols]
    return total


def dead_value(sensor: FSRSensor) -> float:
    """What a dead taxel of ``sensor`` reads: the sensing range (gap mode) or zero pressure (contact mode)."""
    return float(sensor.range_mm) if sensor.mode == "gap" else 0.0


def _sequences(frames, sensor: FSRSensor) -> np.ndarray:
    frames = np.asarray(frames)
    if frames.ndim < 3 or frames.shape[-2:] != (sensor.rows, sensor.cols):
        raise SensorSpecError(
            f"dead taxels: frames must be (..., probes, {sensor.rows}, {sensor.cols}) for this sensor, "
            f"got shape {frames.shape}"
        )
    if not np.isfinite(frames).all():
        raise SensorSpecError("dead taxels: frames contain NaN or Inf")
    return frames


def find_dead_taxels(frames, sensor: FSRSensor, *, max_dead_neighbours: int = 2) -> np.ndarray:
    """(..., R, C) mask of the taxels that look dead in each sequence of ``frames`` (..., P, R, C).

    A taxel is dead when it reads :func:`dead_value` in all P frames of its sequence and at most
    ``max_dead_neighbours`` of its 8 neighbours do as well (module docstring).

    Raises:
        SensorSpecError: frames not shaped (..., P, rows, cols) for ``sensor``, or not finite.
    """
    frames = _sequences(frames, sensor)
    value = dead_value(sensor)
    # The read-out clips to the dead value exactly; a tolerance keeps float16/uint16-decoded frames working.
    tolerance = 1e-3 * max(abs(value), 1.0) if np.issubdtype(frames.dtype, np.floating) else 0
    always = (np.abs(frames - value) <= tolerance).all(axis=-3)
    return always & (_neighbour_sum(always.astype(np.int16)) <= max_dead_neighbours)


def repair_dead_taxels(frames, sensor: FSRSensor, *, max_dead_neighbours: int = 2) -> np.ndarray:
    """``frames`` (..., P, R, C) with each dead taxel (:func:`find_dead_taxels`) replaced, frame by frame, by the
    mean of its live in-bounds neighbours; same dtype. A dead taxel with no live neighbour is left as it is.

    Raises:
        SensorSpecError: frames not shaped (..., P, rows, cols) for ``sensor``, or not finite.
    """
    frames = _sequences(frames, sensor)
    dead = find_dead_taxels(frames, sensor, max_dead_neighbours=max_dead_neighbours)
    if not dead.any():
        return frames.copy()
    live = (~dead)[..., None, :, :].astype(np.float64)  # (..., 1, R, C): the same for every frame
    sums = _neighbour_sum(frames * live)
    counts = _neighbour_sum(np.broadcast_to(live, frames.shape))
    fill = dead[..., None, :, :] & (counts > 0)
    return np.where(fill, sums / np.maximum(counts, 1), frames).astype(frames.dtype)


__all__ = ["dead_value", "find_dead_taxels", "repair_dead_taxels"]
