"""Touching: contours on the object surface, the virtual FSR tactile array pressed along them, datasets."""

from tactile.contours import Contour, Plane, make_contour, plane_through, section
from tactile.dataset import TactileDataset, generate, open_dataset
from tactile.dead_taxels import find_dead_taxels, repair_dead_taxels
from tactile.explore import SequenceBatch, TactileSequence, explore
from tactile.sampling import sample_planes
from tactile.sensor import FSRSensor
from tactile.touching import Toucher, TouchTiming, explore_object, touch, touch_variants

__all__ = [
    "Contour",
    "FSRSensor",
    "Plane",
    "SequenceBatch",
    "TactileDataset",
    "TactileSequence",
    "TouchTiming",
    "Toucher",
    "explore",
    "explore_object",
    "find_dead_taxels",
    "generate",
    "make_contour",
    "open_dataset",
    "plane_through",
    "repair_dead_taxels",
    "sample_planes",
    "section",
    "touch",
    "touch_variants",
]
