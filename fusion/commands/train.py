"""``visuotactile train``: fit a classifier on a dataset store and save it; reports held-out accuracy."""

from __future__ import annotations

import argparse

from fusion.commands import print_json


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.training import train_on_store
    from perception.atomic import check_output_file

    check_output_file(args.out, "--out")  # before training, not after
    result = train_on_store(args.store, args.model, args.out, cue=args.cue, split=args.split,
                            test_fraction=args.test_fraction, strategy=args.strategy, random_state=args.seed,
                            calibrated=args.calibrate, outliers=args.outliers, contrastive=args.contrastive)
    acc = result.pop("accuracy", None)
    if args.json:
        print_json(result)
    else:
        line = (f"trained {args.model} ({args.cue}) on {result['train_sequences']} sequences in "
                f"{result['fit_seconds']:.1f} s -> {args.out}")
        if acc is not None:
            line += f"; held-out {args.split} split ({result['test_sequences']} sequences): {acc.percent()}"
        if "calibration" in result:
            cal = result["calibration"]
            line += (f"; calibrated (temperature {cal['temperature']:g}, touch dependence {cal['dependence']:g}, "
                     + (f"answers 'unknown' by {cal['score'].replace('_', ' ')})" if cal["score"] else
                        "no 'unknown' answer: fewer than three classes)"))
        print(line)
    return 0


def register(sub) -> None:
    from fusion.classifiers import CLASSIFIERS
    from fusion.cues import CUES
    from fusion.training import SPLITS

    p = sub.add_parser("train", help="train a classifier on a dataset store and save it")
    p.add_argument("--store", required=True, help="dataset store written by `visuotactile generate`")
    p.add_argument("--model", choices=CLASSIFIERS, default="cnn", help="classifier (default: cnn)")
    p.add_argument("--out", required=True, help="model file to write (e.g. models/cnn.vtm)")
    p.add_argument("--split", choices=SPLITS, default="sequence",
                   help="hold out test sequences: by sequence (80/20, a repeated contour's copies on one side), by "
                        "object (unseen objects), or none")
    p.add_argument("--test-fraction", type=float, default=0.2, help="held-out share (default: 0.2)")
    p.add_argument("--strategy", default=None, help="train on this strategy's sequences only (default: all)")
    p.add_argument("--cue", choices=CUES, default="invariant",
                   help="kinesthetic cue (default: pose-free invariant cues; normals: the paper's, pose-dependent)")
    p.add_argument("--calibrate", action="store_true",
                   help="also fit calibrated probabilities and an 'unknown' answer on the training objects (held-out "
                        "objects inside the training part; needs >= 3 objects per class; trains several more times)")
    p.add_argument("--outliers", default=None, metavar="STORE",
                   help="cnn only: a store of touches of objects of no class in --store; the nets learn to doubt "
                        "what feels like none of the classes (outlier exposure)")
    p.add_argument("--contrastive", type=float, default=0.0, metavar="WEIGHT",
                   help="cnn only: weight of a supervised contrastive term (0 to 10; default 0: none) that gathers each "
                        "class's touches in the feature space where --calibrate's 'unknown' answer measures distances "
                        "(reproduce's open-set part uses 0.5)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print a JSON result on stdout")
    p.set_defaults(func=run)
