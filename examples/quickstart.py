"""The README's ten lines: attend to a built-in mug, touch it along guided contours, look at the data.

Run: .venv/bin/python examples/quickstart.py
"""

from perception.saliency import saliency
from perception.shapes import make_object
from tactile import touch

mug = make_object("mug", seed=3)  # or perception.load_object("cup.off", label="cup")
attention = saliency(mug, method="multiview")  # per-vertex visual saliency in [0, 1]
sequences = touch(mug, "guided", 5, saliency=attention, seed=0)
print(sequences[0].frames.shape)  # (25, 32, 32) tactile images, mm
print(sequences[0].normals.shape)  # (25, 3) kinesthetic cue
print([round(float(s), 1) for s in sequences[0].pad_sides_mm])  # pad side per probe, mm (shrinks in concave spots)
