"""New-instances benchmark: classifiers trained on one mesh set, tested on other instances of the same classes.

The unseen-objects part of ``visuotactile reproduce`` tests on objects left out of training, but they come from the
set every default was chosen on. This benchmark trains each classifier on all of ``--train`` (default: the shared
SHREC 2007 meshes, both strategies' contours pooled, as the unseen part does) and tests it on the meshes of
``--instances`` (a class-per-folder collection of the same classes that nobody tuned on), upright and each in its
seeded random pose, guided and blind. It reports, per classifier, pose and strategy, the accuracy of one touch and of
K fused touches (log rule, :func:`fusion.experiments.analysis.touches_score`) with 95 % intervals over objects, and
the paired differences guided - blind and any pose - upright (:func:`fusion.experiments.analysis.paired_difference`).

A test mesh whose bytes equal a training mesh's is refused (exit 2, naming both): it would be a seen object.

The 100 SHREC 2007 instances next to the shared ones (instances 11-20 of each class block of the Princeton
segmentation benchmark, which the shared folder's README describes) are what this was written for. They are not
shipped; a user who wants them takes them from that repository's history, e.g.::

    git clone https://github.com/cearto/zen && cd zen
    C=1bb67bbab4b696d1b33828457e283bbaf0382195; P=Code/MeshDeformations/Benchmark/data/off
    for spec in Cup:21 Glasses:41 Airplane:61 Chair:101 Octopus:121 Teddy:161 Hand:181 Plier:201 Fish:221 Bird:241; do
      c=${spec%%:*}; s=${spec##*:}; mkdir -p ../others/$c
      for i in $(seq $((s + 10)) $((s + 19))); do git show $C:$P/$i.off > ../others/$c/$(printf %03d $i).off; done
    done

Stores and models are cached under ``--out`` (default: a temporary folder), so a second run only scores.

    .venv/bin/python -m benchmarks.new_instances --instances DIR [--train DIR] [--contours 24] [--touches 8]
        [--classifiers cnn,svm,knn] [--poses upright,any] [--out DIR] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks._common import DATA, machine
from perception.errors import DatasetError, InvalidArgumentError

STRATEGIES = ("guided", "blind")
POSES = {"upright": "upright", "any": "any pose"}


def seen_copies(train, test) -> list[tuple[Path, Path]]:
    """(test file, training file) pairs whose bytes are equal: test objects that are in fact training objects."""
    from fusion.experiments.data import mesh_digest

    digests = {mesh_digest(p): Path(p) for p, _ in train}
    return [(Path(p), digests[d]) for p, _ in test if (d := mesh_digest(p)) in digests]


def run(instances: Path, train_folder: Path, out: Path, *, contours: int = 24, touches: int = 8,
        classifiers=("cnn", "svm", "knn"), poses=("upright", "any"), seed: int = 0) -> dict:
    """Train on ``train_folder``, test on ``instances`` (module docstring); returns the result as plain data.

    Raises:
        DatasetError: a bad folder, a test class the training set lacks, or a test mesh equal to a training one.
        InvalidArgumentError: an unknown classifier or pose, a seed outside [0, 2**32 - 1], or touches outside
            2..contours.
    """
    from fusion.experiments.analysis import paired_difference, touches_score
    from fusion.experiments.data import any_pose, ensure_store, folder_objects
    from fusion.experiments.models import default_classifiers, digest, pick, train_and_predict

    poses = tuple(dict.fromkeys(poses))
    unknown = [p for p in poses if p not in POSES]
    if unknown:
        raise InvalidArgumentError(f"unknown poses {unknown}; choose from {', '.join(POSES)}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
        # scikit-learn's estimators take seeds below 2**32 only
        raise InvalidArgumentError(f"the seed must be an integer in [0, 2**32 - 1], got {seed!r}")
    if contours < touches or touches < 2:
        raise InvalidArgumentError(f"need 2 <= touches <= contours, got {touches} touches of {contours} contours")
    factories = pick(default_classifiers(seed), classifiers)
    train, test = folder_objects(train_folder), folder_objects(instances)
    missing = sorted({label for _, label in test} - {label for _, label in train})
    if missing:
        raise DatasetError(f"{instances}: classes {missing} are not in the training set {train_folder}")
    copies = seen_copies(train, test)
    if copies:
        raise DatasetError(f"{instances}: {len(copies)} test meshes are training meshes byte for byte "
                           f"(first: {copies[0][0]} = {copies[0][1]}); leave them out")
    ds, record = ensure_store(train, out / "stores", strategies=STRATEGIES, contours=contours, seed=seed)
    index = np.sort(np.concatenate([ds.indices(s) for s in STRATEGIES]))
    loaded: dict = {}

    def training():  # read once, and only when a model must be fitted
        if "batch" not in loaded:
            loaded["batch"] = ds.load(index)
        return loaded["batch"]

    train_record = {"part": "new_instances", "store": digest(record), "train": digest(index)}
    preds: dict = {}
    for pose in poses:
        objects = test if pose == "upright" else any_pose(test, seed)
        tds, test_store = ensure_store(objects, out / "stores", strategies=STRATEGIES, contours=contours, seed=seed)
        for strategy in STRATEGIES:
            rows = tds.indices(strategy)
            for name, factory in factories.items():
                preds[(name, pose, strategy)] = train_and_predict(
                    name, factory, training, lambda rows=rows, tds=tds: tds.load(rows), out / "models", train_record,
                    {"tag": f"{strategy}-{pose}", "test": digest(test_store)})

    def percent(difference: dict) -> dict:
        return {k: (100 * v if k != "n_objects" else v) for k, v in difference.items()}

    rows, differences = [], []
    for (name, pose, strategy), pred in preds.items():
        one, fused = touches_score(pred, 1, seed=seed), touches_score(pred, touches, seed=seed)
        rows.append({"classifier": name, "pose": pose, "strategy": strategy, "objects": len(set(pred.object_ids)),
                     "k1": one.to_dict(), f"k{touches}": fused.to_dict()})
    for name in classifiers:
        for k in (1, touches):
            for pose in poses:
                differences.append({"classifier": name, "k": k, "compare": f"guided - blind ({pose})", **percent(
                    paired_difference(preds[(name, pose, "guided")], preds[(name, pose, "blind")], k, seed=seed))})
            if set(poses) == set(POSES):
                for strategy in STRATEGIES:
                    differences.append({"classifier": name, "k": k, "compare": f"any - upright ({strategy})", **percent(
                        paired_difference(preds[(name, "any", strategy)], preds[(name, "upright", strategy)], k,
                                          seed=seed))})
    return {"machine": machine(), "train": str(train_folder), "instances": str(instances),
            "train_objects": len(train), "test_objects": len(test),
            # objects that failed to load are logged and left out of the stores: report what was tested
            "tested_objects": min((row["objects"] for row in rows), default=0),
            "contours": contours, "touches": touches, "seed": seed, "rows": rows, "differences": differences}


def report(result: dict) -> str:
    k = result["touches"]
    lines = [(f"new instances: trained on {result['train_objects']} objects of {result['train']}, tested on "
              f"{result['tested_objects']} of the {result['test_objects']} objects of {result['instances']} "
              f"({result['contours']} contours per object and strategy; intervals over objects)"), "",
             f"| classifier | pose | strategy | K = 1 | K = {k} |", "|---|---|---|---|---|"]

    def cell(a: dict) -> str:
        return f"{100 * a['value']:.1f} % [{100 * a['low']:.1f}, {100 * a['high']:.1f}]"

    for row in result["rows"]:
        lines.append(f"| {row['classifier']} | {row['pose']} | {row['strategy']} | {cell(row['k1'])} | "
                     f"{cell(row[f'k{k}'])} |")
    lines += ["", "| classifier | K | difference | points [95 % interval] | detectable |", "|---|---|---|---|---|"]
    for d in result["differences"]:
        lines.append(f"| {d['classifier']} | {d['k']} | {d['compare']} | {d['difference']:+.1f} [{d['low']:+.1f}, "
                     f"{d['high']:+.1f}] | {d['detectable']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.new_instances", description=__doc__.split("\n")[0])
    parser.add_argument("--instances", type=Path, required=True, help="class-per-folder meshes to test on")
    parser.add_argument("--train", type=Path, default=DATA / "shrec07", help="class-per-folder meshes to train on")
    parser.add_argument("--contours", type=int, default=24, help="contours per object and strategy")
    parser.add_argument("--touches", type=int, default=8, help="touches fused per decision")
    parser.add_argument("--classifiers", default="cnn,svm,knn")
    parser.add_argument("--poses", default="upright,any", help="upright, any (each object in a random pose), or both")
    parser.add_argument("--out", type=Path, default=None, help="cache folder for stores and models (default: temporary)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        try:
            result = run(args.instances, args.train, args.out or Path(scratch), contours=args.contours,
                         touches=args.touches, classifiers=tuple(args.classifiers.split(",")),
                         poses=tuple(args.poses.split(",")), seed=args.seed)
        except (DatasetError, InvalidArgumentError) as exc:
            print(f"new_instances: {exc}", file=sys.stderr)
            return 2
    print(report(result))
    if args.json:
        print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
