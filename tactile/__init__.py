"""Touching: contours on the object surface and the virtual FSR tactile array pressed along them."""

from tactile.contours import Contour, Plane, make_contour, plane_through, section
from tactile.explore import SequenceBatch, TactileSequence, explore
from tactile.sensor import FSRSensor

__all__ = [
    "Contour",
    "FSRSensor",
    "Plane",
    "SequenceBatch",
    "TactileSequence",
    "explore",
    "make_contour",
    "plane_through",
    "section",
]

from tactile.sampling import explore_object, sample_planes

__all__ += ["explore_object", "sample_planes"]
