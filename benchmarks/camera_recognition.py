"""Camera recognition benchmark: CAD-trained classifiers on virtual-OAK reconstructions next to the CAD meshes.

Training: built-in catalogue objects (every class x ``--train-objects`` seeds 0, 1, ...), blind contours,
one store per sensor setting. Test: other instances of every class (seeds 1000, 1001, ...), each touched
``--touches`` times (blind contours, sum of log-probabilities) twice: on its CAD mesh, and on its reconstruction
from a virtual OAK-D (4 views at 500 mm, stereo noise, :func:`perception.reconstruct.multiview.reconstruct_frames` closed
against the table, as ``visuotactile camera`` does) scaled to the training size.
``--settle`` compares sensor settings: ``settle_mm`` 0 (the pad never settles; it shrinks wherever the surface
pokes through) against the default, each with its own store and models. Timings: reconstruction per object,
touching per object and one decision, median.

    .venv/bin/python -m benchmarks.camera_recognition [--quick] [--json] [--settle 0,1] [--classifiers knn,svm,cnn]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import machine
from fusion.evaluate import accuracy
from perception.camera import VirtualOakCamera
from perception.geometry import DEFAULT_SIZE_MM, ObjectModel, rescale
from perception.reconstruct.multiview import reconstruct_frames
from perception.reconstruct.surface import surface_error
from perception.shapes import CLASSES, make_object
from tactile.dataset import generate, open_dataset
from tactile.explore import SequenceBatch
from tactile.sampling import explore_object
from tactile.sensor import FSRSensor

TEST_SEED = 1000


def _classifier(kind: str, seed: int):
    if kind == "cnn":
        from fusion.cnn import CNNClassifier

        return CNNClassifier(cue="invariant", seed=seed, progress=False)
    from fusion.conventional import ConventionalClassifier

    return ConventionalClassifier(kind=kind, cue="invariant", random_state=seed)


def reconstruct(cls: str, seed: int, views: int, distance_mm: float) -> tuple[ObjectModel, dict, float]:
    """The virtual-OAK reconstruction of catalogue object (cls, seed) at the training size, its surface
    error (mm, against the true mesh) and the capture + reconstruction time (s)."""
    start = time.perf_counter()
    camera = VirtualOakCamera(make_object(cls, seed), seed=seed)
    rec = reconstruct_frames(camera.capture_views(views, distance_mm), target=camera.target, seed=seed)
    elapsed = time.perf_counter() - start
    model = rescale(rec.model, DEFAULT_SIZE_MM, name=f"{cls}/{seed} reconstructed")
    return model, surface_error(rec.model, camera.truth), elapsed


def _decide(clf, sequences, sensor: FSRSensor) -> str:
    from fusion.decide import fuse_touches

    names = [str(c) for c in clf.classes_]
    batch = SequenceBatch.from_sequences(sequences, class_names=names, sensor_spec=sensor.spec())
    return names[int(np.argmax(fuse_touches(clf.predict_proba(batch), rule="log")))]


def run(classes, train_objects: int, test_objects: int, contours: int, touches: int, settles, kinds,
        views: int = 4, distance_mm: float = 500.0, seed: int = 0, progress: bool = True) -> dict:
    """Train per sensor setting, touch every test object's CAD mesh and reconstruction; returns the rows."""
    tests = [(c, TEST_SEED + i) for c in classes for i in range(test_objects)]
    recs, rec_errors, rec_times = {}, [], []
    for cls, s in tests:
        recs[cls, s], error, elapsed = reconstruct(cls, s, views, distance_mm)
        rec_errors.append(error)
        rec_times.append(elapsed)
        if progress:
            print(f"  reconstructed {cls}/{s}: {error['mean_mm']:.2f} mm mean, {elapsed:.1f} s", file=sys.stderr)
    rows, per_object = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for settle in settles:
            sensor = FSRSensor(settle_mm=settle)
            store = Path(tmp) / f"train_settle{settle}.zarr"
            start = time.perf_counter()
            generate([(c, s) for c in classes for s in range(train_objects)], store, strategies=("blind",),
                     contours_per_object=contours, sensor=sensor, seed=seed, progress=False)
            data = open_dataset(store).load()
            gen_s = time.perf_counter() - start
            for kind in kinds:
                start = time.perf_counter()
                clf = _classifier(kind, seed).fit(data)
                fit_s = time.perf_counter() - start
                predictions = {"cad": [], "reconstructed": []}
                touch_times, decide_times, full = [], [], {"cad": [], "reconstructed": []}
                for cls, s in tests:
                    for source, model in (("cad", make_object(cls, s)), ("reconstructed", recs[cls, s])):
                        start = time.perf_counter()
                        sequences = explore_object(model, "blind", touches, sensor=sensor, seed=s)
                        touch_times.append(time.perf_counter() - start)
                        full[source].append(np.mean([np.mean(q.pad_sides_mm >= sensor.side_mm) for q in sequences]))
                        start = time.perf_counter()
                        predicted = _decide(clf, sequences, sensor)
                        decide_times.append(time.perf_counter() - start)
                        predictions[source].append(predicted)
                        per_object.append({"settle_mm": settle, "classifier": kind, "object": f"{cls}/{s}",
                                           "source": source, "predicted": predicted})
                # One decision per object: bootstrap over the objects.
                truth = [cls for cls, _ in tests]
                cad, rec = (accuracy(truth, predictions[k], seed=seed) for k in ("cad", "reconstructed"))
                rows.append({
                    "settle_mm": settle, "classifier": kind, "objects": len(tests),
                    "cad_accuracy": cad.value, "cad_interval": [cad.low, cad.high],
                    "reconstructed_accuracy": rec.value, "reconstructed_interval": [rec.low, rec.high],
                    "full_pads_cad": float(np.mean(full["cad"])),
                    "full_pads_reconstructed": float(np.mean(full["reconstructed"])),
                    "train_sequences": len(data), "generate_s": gen_s, "fit_s": fit_s,
                    "touch_s": statistics.median(touch_times), "decide_s": statistics.median(decide_times),
                })
                if progress:
                    r = rows[-1]
                    print(f"  settle {settle} {kind}: CAD {r['cad_accuracy']:.2f}, reconstructed "
                          f"{r['reconstructed_accuracy']:.2f}", file=sys.stderr)
    return {
        "rows": rows, "per_object": per_object,
        "reconstruction": {
            "mean_mm": statistics.median(e["mean_mm"] for e in rec_errors),
            "p95_mm": statistics.median(e["p95_mm"] for e in rec_errors),
            "seconds": statistics.median(rec_times),
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.camera_recognition", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    parser.add_argument("--quick", action="store_true", help="3 classes, one test object each, kNN only")
    parser.add_argument("--train-objects", type=int, default=3, help="training instances per class (seeds 0..)")
    parser.add_argument("--test-objects", type=int, default=2, help="test instances per class (seeds 1000..)")
    parser.add_argument("--contours", type=int, default=30, help="training contours per object")
    parser.add_argument("--touches", type=int, default=8, help="contours touched per decision")
    parser.add_argument("--settle", default="0,1", help="settle_mm values to compare (comma-separated)")
    parser.add_argument("--classifiers", default="knn,svm,cnn")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    classes, kinds, test_objects = list(CLASSES), args.classifiers.split(","), args.test_objects
    if args.quick:
        classes, kinds, test_objects = classes[:3], ["knn"], 1
    settles = [float(v) for v in args.settle.split(",")]
    result = {"machine": machine(), "settings": {**vars(args), "classes": classes}}
    result.update(run(classes, args.train_objects, test_objects, args.contours, args.touches, settles, kinds,
                      seed=args.seed))
    rec = result["reconstruction"]
    print(f"Reconstructions: {len(classes) * test_objects} objects, surface error median of means "
          f"{rec['mean_mm']:.2f} mm (p95 {rec['p95_mm']:.2f} mm), {rec['seconds']:.1f} s each")
    print(f"{'settle mm':>9} {'classifier':>10} {'CAD acc [95 %]':>18} {'rec acc [95 %]':>18} {'full pads CAD':>13} "
          f"{'full pads rec':>13} {'fit s':>7} {'touch s':>8} {'decide ms':>9}")
    for r in result["rows"]:
        cad = f"{r['cad_accuracy']:.2f} [{r['cad_interval'][0]:.2f}, {r['cad_interval'][1]:.2f}]"
        rec = f"{r['reconstructed_accuracy']:.2f} [{r['reconstructed_interval'][0]:.2f}, {r['reconstructed_interval'][1]:.2f}]"
        print(f"{r['settle_mm']:>9g} {r['classifier']:>10} {cad:>18} {rec:>18} "
              f"{r['full_pads_cad']:>13.2f} {r['full_pads_reconstructed']:>13.2f} {r['fit_s']:>7.1f} "
              f"{r['touch_s']:>8.2f} {1000 * r['decide_s']:>9.1f}")
    if args.json:
        print(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
