"""``visuotactile train``: fit a classifier on a dataset store and save it; reports held-out accuracy."""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from fusion.commands import print_json

log = logging.getLogger(__name__)

SPLITS = ("sequence", "object", "none")


def split_indices(dataset, split: str, strategy: str | None, test_fraction: float, seed: int):
    """(train, test) sequence indices of ``dataset`` for ``split`` (test empty for ``"none"``), restricted to
    ``strategy``'s sequences when given. The same arguments give the same indices (``evaluate`` relies on it)."""
    index = dataset.indices(strategy)
    if split == "none":
        return index, index[:0]
    if split == "sequence":
        return dataset.split_by_sequence(test_fraction=test_fraction, seed=seed, index=index)
    return dataset.split_by_object(test_fraction=test_fraction, seed=seed, index=index)


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.classifiers import make_classifier
    from fusion.evaluate import accuracy
    from tactile.dataset import open_dataset

    dataset = open_dataset(args.store)
    train, test = split_indices(dataset, args.split, args.strategy, args.test_fraction, args.seed)
    model = make_classifier(args.model, cue=args.cue, random_state=args.seed)
    start = time.perf_counter()
    model.fit(dataset.load(train))
    fit_s = time.perf_counter() - start
    # Remembered so that `evaluate` on the same store tests on the same held-out sequences.
    model.training_ = {
        "store": str(args.store),
        "store_id": dataset.attrs.get("store_id", ""),
        "split": args.split,
        "strategy": args.strategy,
        "test_fraction": args.test_fraction,
        "seed": args.seed,
        "train_sequences": len(train),
    }
    model.save(args.out)
    result = {"model": args.model, "cue": args.cue, "out": str(args.out), "train_sequences": len(train),
              "fit_seconds": round(fit_s, 2)}
    if len(test):
        batch = dataset.load(test)
        truth = np.asarray(batch.class_names, dtype=object)[batch.labels]
        acc = accuracy(truth, model.predict(batch), seed=args.seed)
        result.update(test_sequences=len(test), test_accuracy=acc.to_dict())
    if args.json:
        print_json(result)
    else:
        line = f"trained {args.model} ({args.cue}) on {len(train)} sequences in {fit_s:.1f} s -> {args.out}"
        if len(test):
            line += f"; held-out {args.split} split ({len(test)} sequences): {acc.percent()}"
        print(line)
    return 0


def register(sub) -> None:
    from fusion.classifiers import CLASSIFIERS
    from fusion.cues import CUES

    p = sub.add_parser("train", help="train a classifier on a dataset store and save it")
    p.add_argument("--store", required=True, help="dataset store written by `visuotactile generate`")
    p.add_argument("--model", choices=CLASSIFIERS, default="cnn", help="classifier (default: cnn)")
    p.add_argument("--out", required=True, help="model file to write (e.g. models/cnn.vtm)")
    p.add_argument("--split", choices=SPLITS, default="sequence",
                   help="hold out test sequences: by sequence (the paper's 80/20), by object (unseen objects), or none")
    p.add_argument("--test-fraction", type=float, default=0.2, help="held-out share (default: 0.2)")
    p.add_argument("--strategy", default=None, help="train on this strategy's sequences only (default: all)")
    p.add_argument("--cue", choices=CUES, default="invariant",
                   help="kinesthetic cue (default: pose-free invariant cues; normals: the paper's, pose-dependent)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print a JSON result on stdout")
    p.set_defaults(func=run)
