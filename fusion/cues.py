"""Kinesthetic cues: what the finger's pose tells at each probe, as (S, P, k) arrays for the classifiers.

- ``"normals"``: the paper's cue, the unit outward surface normal in the object's frame (k = 3). It depends
  on how each object happens to be posed.
- ``"invariant"``: pose-invariant cues (k = 6), unchanged by any rotation or translation of the object:
  ``radial_mm`` (probe distance from the plane point, the object centre), ``normal_out_of_plane`` (normal .
  plane normal), ``normal_radial`` (normal . unit radial direction), ``tangent_radial`` (pad x axis . unit
  radial direction: how fast the finger moves away from the centre), ``pad_side_mm`` (the adaptive pad's
  side) and ``step_mm`` (distance to the next probe, closing the loop: the contour's perimeter / P).
  The contour's direction and the plane normal's sign are arbitrary, so ``normal_out_of_plane`` and
  ``tangent_radial`` may flip sign together with the probe order; a classifier should see both.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from perception.errors import InvalidArgumentError

if TYPE_CHECKING:  # the command line imports CUES without loading the geometry stack
    from tactile.explore import SequenceBatch

CUES = ("normals", "invariant")
INVARIANT_NAMES = ("radial_mm", "normal_out_of_plane", "normal_radial", "tangent_radial", "pad_side_mm", "step_mm")


def cue_width(cue: str) -> int:
    """Channels per probe of ``cue``."""
    check_cue(cue)
    return 3 if cue == "normals" else len(INVARIANT_NAMES)


def check_cue(cue: str) -> None:
    if cue not in CUES:
        raise InvalidArgumentError(f"unknown kinesthetic cue {cue!r}; choose one of {', '.join(CUES)}")


def kinesthetic_cues(batch: SequenceBatch, cue: str = "normals") -> np.ndarray:
    """(S, P, k) float32 kinesthetic cue of every probe of ``batch`` (see the module docstring).

    Raises:
        DatasetError: unknown cue.
    """
    check_cue(cue)
    normals = np.asarray(batch.normals, dtype=np.float64)
    if cue == "normals":
        return normals.astype(np.float32)
    radial = np.asarray(batch.positions, dtype=np.float64) - np.asarray(batch.plane_points)[:, None, :]
    distance = np.linalg.norm(radial, axis=-1)
    # A probe at the centre has no radial direction: its radial cosines are 0, not NaN.
    unit_radial = radial / np.where(distance > 1e-9, distance, np.inf)[..., None]
    plane_normals = np.asarray(batch.plane_normals, dtype=np.float64)[:, None, :]
    tangents = np.asarray(batch.tangents, dtype=np.float64)
    step = np.linalg.norm(np.roll(batch.positions, -1, axis=1) - batch.positions, axis=-1)
    out = np.stack(
        [
            distance,
            np.sum(normals * plane_normals, axis=-1),
            np.sum(normals * unit_radial, axis=-1),
            np.sum(tangents * unit_radial, axis=-1),
            np.asarray(batch.pad_sides_mm, dtype=np.float64),
            step,
        ],
        axis=-1,
    )
    return out.astype(np.float32)


__all__ = ["CUES", "INVARIANT_NAMES", "check_cue", "cue_width", "kinesthetic_cues"]
