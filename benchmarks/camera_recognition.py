"""Camera recognition benchmark: classifiers trained on catalogue objects, tested on virtual-OAK reconstructions
of other instances next to their CAD meshes.

Training: built-in catalogue objects (every class x ``--train-objects`` seeds 0, 1, ...), blind contours,
one store per sensor setting, taken from the objects' CAD meshes, from their virtual captures
(:func:`tactile.captures.virtual_capture`: the same camera and reconstruction as the test objects, of the
*training* instances) or from both (``--train-source``, several to compare). Test: other instances of every class
(seeds 1000, 1001, ...; ``--validation`` takes seeds 500, 501, ... instead, held-out instances to choose a method
on without looking at the test objects), each touched ``--touches`` times (blind contours, sum of
log-probabilities) twice: on its CAD mesh, and on its reconstruction from a virtual OAK-D (4 views at 500 mm,
stereo noise, :func:`perception.reconstruct.multiview.reconstruct_frames` closed against the table, as
``visuotactile camera`` does) scaled to the training size.
``--settle`` compares sensor settings: ``settle_mm`` 0 (the pad never settles; it shrinks wherever the surface
pokes through) against the default, each with its own store and models. Timings: reconstruction per object,
touching per object and one decision, median.

    .venv/bin/python -m benchmarks.camera_recognition [--quick] [--json] [--settle 0,1] [--classifiers knn,svm,cnn]
        [--train-source cad,both] [--validation] [--workers 1]
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
from perception.reconstruct.surface import surface_error
from perception.shapes import CLASSES, make_object
from tactile import touch
from tactile.captures import SOURCES, is_capture, training_specs, virtual_capture
from tactile.dataset import generate, open_dataset
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor

TEST_SEED = 1000
#: First seed of the validation instances (``--validation``): neither training (0, 1, ...) nor test objects.
VALIDATION_SEED = 500


def _classifier(kind: str, seed: int, threads: int | None):
    if kind == "cnn":
        from fusion.cnn import CNNClassifier

        return CNNClassifier(cue="invariant", random_state=seed, progress=False, threads=threads)
    from fusion.conventional import ConventionalClassifier

    return ConventionalClassifier(kind=kind, cue="invariant", random_state=seed)


def _decide(clf, sequences, sensor: FSRSensor) -> str:
    from fusion.decide import fuse_touches

    names = [str(c) for c in clf.classes_]
    batch = SequenceBatch.from_sequences(sequences, class_names=names, sensor_spec=sensor.spec())
    return names[int(np.argmax(fuse_touches(clf.predict_proba(batch), rule="log")))]


def _subset(data, source: str) -> np.ndarray:
    """Sequence indices of the training objects of ``source`` in a store of :func:`training_specs`."""
    capture = np.array([is_capture(n) for n in data.object_names])[data.object_ids]
    if source == "cad":
        return np.flatnonzero(~capture)
    return np.flatnonzero(capture) if source == "capture" else np.arange(len(data))


def run(classes, train_objects: int, test_objects: int, contours: int, touches: int, settles, kinds,
        sources=("cad",), views: int = 4, distance_mm: float = 500.0, seed: int = 0, first_test_seed: int = TEST_SEED,
        workers: int | None = 1, threads: int | None = None, captures_per_object: int = 1,
        progress: bool = True) -> dict:
    """Train per sensor setting and training source, touch every test object's CAD mesh and reconstruction;
    returns the rows."""
    train = [(c, s) for c in classes for s in range(train_objects)]
    tests = [(c, first_test_seed + i) for c in classes for i in range(test_objects)]
    if {s for _, s in train} & {s for _, s in tests}:
        raise ValueError("training and test objects must be different instances (disjoint seeds)")
    recs, rec_errors, rec_times = {}, [], []
    for cls, s in tests:
        capture = virtual_capture(make_object(cls, s), views=views, distance_mm=distance_mm, seed=s)
        recs[cls, s] = capture.model
        error = surface_error(capture.world, capture.truth)
        rec_errors.append(error)
        rec_times.append(capture.seconds)
        if progress:
            print(f"  reconstructed {cls}/{s}: {error['mean_mm']:.2f} mm mean, {capture.seconds:.1f} s", file=sys.stderr)
    store_source = "cad" if set(sources) == {"cad"} else "capture" if set(sources) == {"capture"} else "both"
    rows, per_object = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for settle in settles:
            sensor = FSRSensor(settle_mm=settle)
            store = Path(tmp) / f"train_settle{settle}.zarr"
            start = time.perf_counter()
            report = generate(training_specs(train, store_source, views=views, distance_mm=distance_mm,
                                             captures_per_object=captures_per_object), store,
                              strategies=("blind",), contours_per_object=contours, sensor=sensor, seed=seed,
                              workers=workers, progress=False)
            if report.failed:
                raise RuntimeError(f"training objects failed: {report.failed}")
            dataset = open_dataset(store)
            gen_s = time.perf_counter() - start
            touched, touch_times = {}, []
            for source in sources:
                data = dataset.load(_subset(dataset, source))
                for kind in kinds:
                    start = time.perf_counter()
                    clf = _classifier(kind, seed, threads).fit(data)
                    fit_s = time.perf_counter() - start
                    predictions = {"cad": [], "reconstructed": []}
                    decide_times, full = [], {"cad": [], "reconstructed": []}
                    for cls, s in tests:
                        for tested in ("cad", "reconstructed"):
                            if (tested, cls, s) not in touched:  # the same touches for every classifier
                                start = time.perf_counter()
                                model = make_object(cls, s) if tested == "cad" else recs[cls, s]
                                touched[tested, cls, s] = touch(model, "blind", touches, sensor=sensor, seed=s)
                                touch_times.append(time.perf_counter() - start)
                            sequences = touched[tested, cls, s]
                            full[tested].append(np.mean([np.mean(q.pad_sides_mm >= sensor.side_mm) for q in sequences]))
                            start = time.perf_counter()
                            predicted = _decide(clf, sequences, sensor)
                            decide_times.append(time.perf_counter() - start)
                            predictions[tested].append(predicted)
                            per_object.append({"settle_mm": settle, "train_source": source, "classifier": kind,
                                               "object": f"{cls}/{s}", "source": tested, "predicted": predicted})
                    # One decision per object: bootstrap over the objects.
                    truth = [cls for cls, _ in tests]
                    cad, rec = (accuracy(truth, predictions[k], seed=seed) for k in ("cad", "reconstructed"))
                    rows.append({
                        "settle_mm": settle, "train_source": source, "classifier": kind, "objects": len(tests),
                        "cad_accuracy": cad.value, "cad_interval": [cad.low, cad.high],
                        "reconstructed_accuracy": rec.value, "reconstructed_interval": [rec.low, rec.high],
                        "full_pads_cad": float(np.mean(full["cad"])),
                        "full_pads_reconstructed": float(np.mean(full["reconstructed"])),
                        "train_sequences": len(data), "generate_s": gen_s, "fit_s": fit_s,
                        "touch_s": statistics.median(touch_times), "decide_s": statistics.median(decide_times),
                    })
                    if progress:
                        r = rows[-1]
                        print(f"  settle {settle} {source} {kind}: CAD {r['cad_accuracy']:.2f}, reconstructed "
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
    parser.add_argument("--validation", action="store_true",
                        help=f"test on held-out instances (seeds {VALIDATION_SEED}..), not the test objects")
    parser.add_argument("--contours", type=int, default=30, help="training contours per object")
    parser.add_argument("--touches", type=int, default=8, help="contours touched per decision")
    parser.add_argument("--settle", default="0,1", help="settle_mm values to compare (comma-separated)")
    parser.add_argument("--train-source", default="cad,both",
                        help=f"training objects to compare (comma-separated: {', '.join(SOURCES)}): CAD meshes, "
                             "their virtual captures, or both")
    parser.add_argument("--captures", type=int, default=1, help="virtual captures per training object")
    parser.add_argument("--classifiers", default="knn,svm,cnn")
    parser.add_argument("--workers", type=int, default=1, help="processes generating the training store")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads of the CNN (default: the cores)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    classes, kinds, test_objects = list(CLASSES), args.classifiers.split(","), args.test_objects
    sources = args.train_source.split(",")
    if args.quick:
        classes, kinds, test_objects = classes[:3], ["knn"], 1
    unknown = [s for s in sources if s not in SOURCES]
    if unknown:
        parser.error(f"unknown --train-source {unknown}; choose from {', '.join(SOURCES)}")
    if args.validation and args.train_objects > VALIDATION_SEED:
        parser.error(f"--validation needs --train-objects <= {VALIDATION_SEED}")
    settles = [float(v) for v in args.settle.split(",")]
    first = VALIDATION_SEED if args.validation else TEST_SEED
    result = {"machine": machine(), "settings": {**vars(args), "classes": classes, "first_test_seed": first}}
    result.update(run(classes, args.train_objects, test_objects, args.contours, args.touches, settles, kinds,
                      sources=sources, seed=args.seed, first_test_seed=first, workers=args.workers,
                      threads=args.threads, captures_per_object=args.captures))
    rec = result["reconstruction"]
    which = "validation" if args.validation else "test"
    print(f"Reconstructions: {len(classes) * test_objects} {which} objects (seeds {first}..), surface error median "
          f"of means {rec['mean_mm']:.2f} mm (p95 {rec['p95_mm']:.2f} mm), {rec['seconds']:.1f} s each")
    print(f"{'settle mm':>9} {'trained on':>10} {'classifier':>10} {'CAD acc [95 %]':>18} {'rec acc [95 %]':>18} "
          f"{'full pads CAD':>13} {'full pads rec':>13} {'fit s':>7} {'touch s':>8} {'decide ms':>9}")
    for r in result["rows"]:
        cad = f"{r['cad_accuracy']:.2f} [{r['cad_interval'][0]:.2f}, {r['cad_interval'][1]:.2f}]"
        rec = f"{r['reconstructed_accuracy']:.2f} [{r['reconstructed_interval'][0]:.2f}, {r['reconstructed_interval'][1]:.2f}]"
        print(f"{r['settle_mm']:>9g} {r['train_source']:>10} {r['classifier']:>10} {cad:>18} {rec:>18} "
              f"{r['full_pads_cad']:>13.2f} {r['full_pads_reconstructed']:>13.2f} {r['fit_s']:>7.1f} "
              f"{r['touch_s']:>8.2f} {1000 * r['decide_s']:>9.1f}")
    if args.json:
        print(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
