"""Recognition from RGB-D captures: a virtual OAK-D photographs a built-in mug from four sides, the frames
are recorded and replayed, the mug is rebuilt from them and touched along contours like a CAD mesh.

Run: .venv/bin/python examples/camera_demo.py [MODEL]    (MODEL: a classifier saved by `visuotactile train`)
With a live camera, replace the virtual one by `with OakCamera() as cam: frames = [cam.capture()]`.
"""

import sys
import tempfile

from perception.camera import VirtualOakCamera, read_recording, write_recording
from perception.geometry import rescale
from perception.reconstruct.multiview import reconstruct_frames
from perception.reconstruct.surface import surface_error
from perception.shapes import make_object
from tactile import touch
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor

mug = make_object("mug", seed=3)
camera = VirtualOakCamera(mug, seed=0)  # OAK-D geometry (75 mm baseline, 640 x 400) and stereo noise
frames = camera.capture_views(4, distance_mm=500.0)  # four RGB-D frames around the table, poses known
with tempfile.TemporaryDirectory(prefix="camera_demo_") as folder:
    write_recording(folder, frames)  # colour PNG, 16-bit depth PNG, JSON
    frames = read_recording(folder)  # ... replays without a device
# Table removed, mug segmented, views fused, Poisson; closed where no camera saw it (the bottom on the table,
# the inside below the sight lines) from the space the frames left uncarved.
rec = reconstruct_frames(frames, target=camera.target)
error = surface_error(rec.model, camera.truth, seen=rec.points)
print(f"reconstructed {rec.model.n_triangles} triangles from {len(rec.points)} points "
      f"(+{len(rec.support)} unseen, closed: {rec.model.is_watertight}): "
      f"mean error {error['mean_mm']:.2f} mm, p95 {error['p95_mm']:.2f} mm "
      f"(where a camera looked: {error['seen_mean_mm']:.2f} / {error['seen_p95_mm']:.2f} mm)")

obj = rescale(rec.model, name="captured mug")  # the 150 mm size the classifiers are trained at
model = None
if len(sys.argv) > 1:
    from fusion.base import load_model

    model = load_model(sys.argv[1])
sensor = model.sensor() if model else FSRSensor()  # record with the sensor the model was trained with
probes = model.probes if model else 25
sequences = touch(obj, "blind", 4, sensor, probes, seed=0)
batch = SequenceBatch.from_sequences(
    sequences, class_names=list(model.classes_) if model else None, sensor_spec=sensor.spec()
)
print(batch.frames.shape)  # (4, 25, 32, 32): contours x probes x taxels
if model:
    from fusion.decide import fuse_touches

    proba = fuse_touches(model.predict_proba(batch), rule="log")
    print("recognized:", model.classes_[int(proba.argmax())], f"({proba.max():.2f})")
