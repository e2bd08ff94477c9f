"""Objects, geometry and visual attention: the bottom of the visuotactile stack."""

from perception.errors import VisuotactileError
from perception.geometry import Curvature, ObjectModel, load_dataset, load_object
from perception.shapes import CLASSES, make_object

__all__ = ["CLASSES", "Curvature", "ObjectModel", "VisuotactileError", "load_dataset", "load_object", "make_object"]
