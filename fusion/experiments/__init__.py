"""Experiments and reports: the paper's protocol and beyond (unseen objects, K touches, noise, attention
models, recognition error against run time), as report folders (Markdown + PNG + JSON).

Entry points: :func:`reproduce` (``visuotactile reproduce``) and :func:`fusion.demo.run_demo`
(``visuotactile demo``), which reuses the same machinery on the built-in catalogue.
"""

from fusion.experiments.config import FULL, QUICK, Sizes
from fusion.experiments.reproduce import PARTS, reproduce

__all__ = ["FULL", "PARTS", "QUICK", "Sizes", "reproduce"]
