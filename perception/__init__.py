"""Objects, geometry and visual attention: the bottom of the visuotactile stack."""

from perception.errors import VisuotactileError
from perception.geometry import Curvature, ObjectModel, load_dataset, load_object

__all__ = ["Curvature", "ObjectModel", "VisuotactileError", "load_dataset", "load_object"]
