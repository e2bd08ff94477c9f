"""``visuotactile evaluate``: a saved model on a dataset store, by sequence or with K touches per decision."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fusion.commands import print_json


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.base import load_model
    from fusion.commands.train import split_indices
    from fusion.decide import touch_groups
    from fusion.evaluate import accuracy, confusion, per_class_accuracy, plot_confusion
    from tactile.dataset import open_dataset

    model = load_model(args.model, trust_pickle=args.trust_pickle)
    dataset = open_dataset(args.store)
    info = getattr(model, "training_", {})
    same_store = info and info.get("store_id", "") == dataset.attrs.get("store_id", "") and \
        Path(info.get("store", "")).resolve() == Path(args.store).resolve()
    if same_store and info.get("split", "none") != "none":
        # Test only on what training held out.
        _, index = split_indices(dataset, info["split"], info.get("strategy"), info["test_fraction"], info["seed"])
        subset = f"held-out {info['split']} split of training"
    else:
        index = dataset.indices(args.strategy)
        subset = "all sequences" + (f" of strategy {args.strategy}" if args.strategy else "")
    batch = dataset.load(index)
    proba = model.predict_proba(batch)
    classes = model.classes_.astype(str)
    truth = np.asarray(batch.class_names, dtype=object)[batch.labels].astype(str)
    if args.touches > 1:
        groups = touch_groups(batch.object_ids, args.touches, seed=args.seed)
        from fusion.decide import fuse_touches

        proba = fuse_touches(proba[groups], rule=args.rule)
        truth = truth[groups[:, 0]]
        decision_groups = batch.object_ids[groups[:, 0]]
    else:
        decision_groups = batch.object_ids
    predicted = classes[np.argmax(proba, axis=1)]
    acc = accuracy(truth, predicted, seed=args.seed)
    by_object = accuracy(truth, predicted, groups=decision_groups, seed=args.seed)
    result = {
        "model": str(args.model), "store": str(args.store), "subset": subset, "touches": args.touches,
        "rule": args.rule, "decisions": len(predicted), "accuracy": acc.to_dict(),
        "accuracy_object_bootstrap": by_object.to_dict(),
        "per_class": per_class_accuracy(truth, predicted, classes),
    }
    if args.figure:
        plot_confusion(confusion(truth, predicted, classes), classes, args.figure,
                       title=f"{Path(args.model).name}, K = {args.touches}: {acc.percent()}")
        result["figure"] = str(args.figure)
    if args.json:
        print_json(result)
    else:
        print(f"{args.model} on {args.store} ({subset}), K = {args.touches} touches ({args.rule} rule): "
              f"{acc.percent()} over {len(predicted)} decisions (interval resampling objects: "
              f"[{100 * by_object.low:.1f}, {100 * by_object.high:.1f}])")
        for name, value in result["per_class"].items():
            print(f"  {name:>14s}: " + ("-" if value is None else f"{100 * value:.1f} %"))
    return 0


def register(sub) -> None:
    from fusion.decide import RULES

    p = sub.add_parser("evaluate", help="evaluate a saved model on a dataset store")
    p.add_argument("--model", required=True, help="model file written by `visuotactile train` or the demo")
    p.add_argument("--store", required=True, help="dataset store")
    p.add_argument("--trust-pickle", action="store_true",
                   help="also load an old pickled model (runs code from the file: only for files you made)")
    p.add_argument("--touches", type=int, default=1, help="sequences of the same object per decision (default: 1)")
    p.add_argument("--rule", choices=RULES, default="log", help="multi-touch fusion rule (default: log)")
    p.add_argument("--strategy", default=None, help="only this strategy's sequences (other stores)")
    p.add_argument("--figure", default=None, help="write a confusion-matrix PNG here")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print a JSON result on stdout")
    p.set_defaults(func=run)
