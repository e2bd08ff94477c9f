"""Classifier benchmark: accuracy next to training time and inference time per sequence.

Classifiers: the CNN pair (``CNNClassifier``; one fit gives the cutaneous, kinesthetic and fused rows) with
the paper's normals and with pose-invariant cues, and the conventional pipeline
(``ConventionalClassifier(kind="svm" | "knn")``, skipped when :mod:`fusion.conventional` is not there).

Data: by default (``--quick``) a small guided batch from the built-in catalogue (every class, ``--objects``
objects x ``--contours`` contours each); with ``--store PATH`` a dataset store (``--strategy`` picks one).
Split 80/20 by sequence (the paper's protocol; seeded, stratified) or by object (``--split object``:
test objects unseen in training). Times are wall seconds on this machine: training includes the
preprocessing; inference is ``predict_proba`` on the whole test part, per sequence (median of
``--repeats``). The CNN rows also give the median epoch time of each net beside its limit measured in the same run
(:func:`training_limit`: the forward and backward passes of an epoch's batches and nothing else; ratio = limit /
epoch, 1 at best).

``--epoch-timing N`` adds a projection: one CNN epoch of each net on N synthetic 25 x 32 x 32 sequences
(default off; 18,240 is the paper-scale training set), scaled to 18,240 sequences, times the epochs the
fitted nets ran (or 50, the paper's, when no fit ran), cut to what the CNN's default step cap allows there.

    .venv/bin/python -m benchmarks.classifiers [--quick] [--store PATH] [--json] [--epochs N] ...
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

import numpy as np

from benchmarks._common import machine, median_time
from fusion.commands import positive_int

log = logging.getLogger(__name__)
PAPER_TRAIN = 18_240
#: Paper accuracies (guided / blind), Rouhafzay & Cretu 2019, Table 1.
PAPER = {"cnn": (98.97, 83.29), "svm": (88.44, 77.21), "knn": (86.07, 73.11)}


def catalogue_batch(objects: int, contours: int, strategy: str, seed: int):
    """Every catalogue class, ``objects`` instances each, ``contours`` sequences per instance."""
    from perception.shapes import CLASSES, make_object
    from tactile import touch
    from tactile.explore import SequenceBatch
    from tactile.sensor import FSRSensor

    sequences = []
    for c, name in enumerate(CLASSES):
        for k in range(objects):
            sequences += touch(make_object(name, k), strategy, contours, seed=seed + 1000 * c + k)
    return SequenceBatch.from_sequences(sequences, CLASSES, sensor_spec=FSRSensor().spec())


def split(batch, how: str, seed: int, test_fraction: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Seeded stratified (train, test) indices of an in-memory batch, by sequence or by object."""
    rng = np.random.default_rng(seed)
    test = []
    for c in np.unique(batch.labels):
        if how == "sequence":
            members = rng.permutation(np.flatnonzero(batch.labels == c))
            test.append(members[: round(test_fraction * len(members))])
        else:
            objects = rng.permutation(np.unique(batch.object_ids[batch.labels == c]))
            if len(objects) >= 2:
                held = objects[: max(1, round(test_fraction * len(objects)))]
                test.append(np.flatnonzero(np.isin(batch.object_ids, held)))
    test = np.sort(np.concatenate(test))
    return np.setdiff1d(np.arange(len(batch)), test), test


def _accuracy(classes, proba, batch) -> float:
    names = np.asarray(batch.class_names, dtype=object)[batch.labels]
    return float(np.mean(np.asarray(classes)[proba.argmax(1)].astype(str) == names.astype(str)))


def cnn_rows(train, test, cue: str, args) -> list[dict]:
    from fusion.cnn import CNNClassifier

    frame = {} if args.frame_size is None else {"frame_size": args.frame_size}
    model = CNNClassifier(cue=cue, epochs=args.epochs, random_state=args.seed, threads=args.threads,
                          progress=not args.json, **frame)
    start = time.perf_counter()
    model.fit(train)
    fit_s = time.perf_counter() - start
    infer_s, proba = median_time(lambda: model.predict_proba_modalities(test), args.repeats)
    limits = training_limit(model, train, args.threads) if model.val_fraction == 0 else {}
    rows = []
    for modality in ("cutaneous", "kinesthetic", "fusion"):
        history = model.history_.get(modality, {})
        rows.append({
            "classifier": f"cnn-{modality}", "cue": cue if modality != "cutaneous" else "-",
            "accuracy_pct": 100 * _accuracy(model.classes_, proba[modality], test),
            # a fusion model trains both nets: its training time is the pair's
            "train_s": fit_s if modality == "fusion" else None,
            "infer_ms_per_seq": 1000 * infer_s / len(test) if modality == "fusion" else None,
            "epochs": history.get("epochs"), "epoch_s": getattr(model, "epoch_seconds_", {}).get(modality),
            "limit_epoch_s": limits.get(modality, {}).get("limit_epoch_s"),
            "limit_ratio": limits.get(modality, {}).get("ratio"),
        })
    return rows


def training_limit(model, train, threads: int | None, steps: int = 100) -> dict:
    """Each net of CNN ``model``, fitted on the batch ``train``, beside its limit: the seconds of one forward and
    backward pass (cross-entropy, no optimizer step, no augmentation, no batch gathered from the data) on a batch of
    the fit's size and input shape, on the fit's threads (the fastest mean of 5 blocks of ``steps`` / 5 passes), times
    the batches of one epoch. Returns {net: {"epoch_s": the fit's median epoch, "limit_epoch_s", "ratio": limit /
    epoch}}; a ratio near 1 leaves nothing but the arithmetic."""
    import copy

    import torch
    from torch.nn import functional as F

    from fusion.cnn import _torch_settings
    from fusion.cues import cue_width
    from perception.runtime import usable_cores

    full, rest = divmod(len(train), model.batch_size)  # every training sequence (no validation part by default)
    sizes = {model.batch_size: full, **({rest: 1} if rest >= 2 else {})}  # a last batch of one is skipped
    frame = tuple(min(n, model.frame_size) for n in train.grid)  # the frames are pooled to at most frame_size
    out = {}
    with _torch_settings(threads or usable_cores(), deterministic=True), torch.random.fork_rng([]):
        torch.manual_seed(0)
        for kind, net in (("cutaneous", model.cutaneous_net_), ("kinesthetic", model.kinesthetic_net_)):
            if net is None or kind not in model.epoch_seconds_:
                continue
            net = copy.deepcopy(net).train()
            p = train.n_probes
            shape = (1, p, *frame) if kind == "cutaneous" else (1, p, cue_width(model.cue))
            limit = 0.0
            for size, count in sizes.items():
                if not count:
                    continue
                x, y = torch.randn(size, *shape), torch.randint(0, len(model.classes_), (size,))
                times = []
                for i in range(steps + 5):
                    start = time.perf_counter()
                    net.zero_grad(set_to_none=True)
                    F.cross_entropy(net(x), y, label_smoothing=model.label_smoothing).backward()
                    if i >= 5:  # the first passes warm the kernels' caches
                        times.append(time.perf_counter() - start)
                # the fastest of 5 blocks' mean pass: the rate the machine sustains at best, not one lucky pass
                blocks = np.array_split(times, min(5, len(times)))
                limit += min(float(np.mean(block)) for block in blocks) * count
            epoch = float(model.epoch_seconds_[kind])
            out[kind] = {"epoch_s": epoch, "limit_epoch_s": limit, "ratio": limit / epoch if epoch > 0 else None}
    return out


def conventional_rows(train, test, args) -> list[dict]:
    try:
        from fusion.conventional import ConventionalClassifier
    except ImportError as exc:
        log.warning("skipping SVM / kNN: fusion.conventional is not available (%s)", exc)
        return []
    rows = []
    for kind in ("svm", "knn"):
        model = ConventionalClassifier(kind=kind)
        start = time.perf_counter()
        model.fit(train)
        fit_s = time.perf_counter() - start
        infer_s, proba = median_time(lambda: model.predict_proba(test), args.repeats)  # noqa: B023
        rows.append({"classifier": kind, "cue": "normals", "accuracy_pct": 100 * _accuracy(model.classes_, proba, test),
                     "train_s": fit_s, "infer_ms_per_seq": 1000 * infer_s / len(test), "epochs": None,
                     "epoch_s": None})
    return rows


def epoch_projection(n: int, epochs_run: dict | None, seed: int, threads: int | None) -> dict:
    """One epoch of each net on ``n`` synthetic 25 x 32 x 32 sequences, scaled to the paper's 18,240 and
    multiplied by the epochs each net would run on those 18,240: the epochs it ran in the benchmark's fit
    (``epochs_run``; the default ``CNNClassifier.epochs`` without one), cut to what the net's default step cap
    (``CNNClassifier.max_steps``) allows."""
    from fusion.cnn import CNNClassifier
    from tactile.explore import SequenceBatch
    from tactile.sensor import FSRSensor

    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 25, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    batch = SequenceBatch(
        frames=rng.uniform(0, 10, (n, 25, 32, 32)).astype(np.float32), normals=normals,
        positions=(50 * normals).astype(np.float32), tangents=np.roll(normals, 1, axis=-1),
        pad_sides_mm=np.full((n, 25), 20.0, np.float32), plane_points=np.zeros((n, 3)),
        plane_normals=np.tile([0.0, 0.0, 1.0], (n, 1)), labels=rng.integers(0, 8, n),
        object_ids=np.zeros(n, np.int64), class_names=tuple(f"c{i}" for i in range(8)),
        sensor_spec=FSRSensor().spec(),
    )
    model = CNNClassifier(epochs=1, val_fraction=0.0, threads=threads, progress=False, random_state=seed)
    model.fit(batch)
    paper_epoch_s = {k: seconds * PAPER_TRAIN / n for k, seconds in model.epoch_seconds_.items()}
    default = CNNClassifier()
    # the default epochs, or fewer under each net's step cap
    epochs = {k: min((epochs_run or {}).get(k) or default.epochs, default.epochs_for(PAPER_TRAIN, k))
              for k in paper_epoch_s}
    total_s = sum(paper_epoch_s[k] * epochs[k] for k in paper_epoch_s)
    return {"sequences": n, "paper_epoch_s": paper_epoch_s, "epochs": epochs, "projected_train_min": total_s / 60}


def _print_table(rows: list[dict]) -> None:
    columns = [("classifier", "classifier"), ("cue", "cue"), ("acc %", "accuracy_pct"), ("train s", "train_s"),
               ("infer ms/seq", "infer_ms_per_seq"), ("epochs", "epochs"), ("epoch s", "epoch_s"),
               ("limit epoch s", "limit_epoch_s"), ("limit ratio", "limit_ratio")]
    widths = [max(len(head), 12) for head, _ in columns]
    print("  ".join(head.rjust(w) for (head, _), w in zip(columns, widths)))
    for row in rows:
        cells = []
        for (_, key), w in zip(columns, widths):
            value = row.get(key)
            cells.append(("" if value is None else f"{value:.4g}" if isinstance(value, float) else str(value)).rjust(w))
        print("  ".join(cells))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.classifiers", description=__doc__.split("\n")[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    parser.add_argument("--quick", action="store_true", help="a small catalogue batch (the default without --store)")
    parser.add_argument("--store", help="a dataset store to read instead of the catalogue")
    parser.add_argument("--strategy", default="guided", help="contour strategy (catalogue or store)")
    parser.add_argument("--split", choices=("sequence", "object"), default="sequence")
    parser.add_argument("--objects", type=int, default=3, help="catalogue objects per class")
    parser.add_argument("--contours", type=int, default=20, help="catalogue contours per object")
    parser.add_argument("--epochs", type=int, default=50, help="most CNN epochs per net")
    parser.add_argument("--cues", default="normals,invariant", help="CNN kinesthetic cues to run, comma-separated")
    parser.add_argument("--no-conventional", action="store_true", help="skip the SVM / kNN rows")
    parser.add_argument("--epoch-timing", type=int, default=0, metavar="N",
                        help="also time one CNN epoch on N synthetic sequences and project to 18,240")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads for the CNNs (default: all usable)")
    parser.add_argument("--frame-size", type=positive_int, default=None, metavar="N",
                        help="taxels a side the CNNs pool frames to (default: the classifier's 16; the paper's "
                             "models in reproduce: 8)")
    parser.add_argument("--repeats", type=int, default=3, help="inference timing repeats (median)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    if args.store:
        from tactile.dataset import open_dataset

        dataset = open_dataset(args.store)
        index = dataset.indices(args.strategy)
        pick = dataset.split_by_sequence if args.split == "sequence" else dataset.split_by_object
        train_idx, test_idx = pick(0.2, seed=args.seed, index=index)
        train, test = dataset.load(train_idx), dataset.load(test_idx)
        source = {"store": str(args.store), "strategy": args.strategy}
    else:
        batch = catalogue_batch(args.objects, args.contours, args.strategy, args.seed)
        train_idx, test_idx = split(batch, args.split, args.seed)
        train, test = batch.subset(train_idx), batch.subset(test_idx)
        source = {"catalogue": f"{len(batch.class_names)} classes x {args.objects} objects x {args.contours} "
                               f"contours", "strategy": args.strategy}
    print(f"data: {source}, split by {args.split}: {len(train)} train / {len(test)} test sequences, "
          f"{train.n_probes} probes of {train.grid[0]} x {train.grid[1]} taxels")

    rows = []
    for cue in [c.strip() for c in args.cues.split(",") if c.strip()]:
        rows += cnn_rows(train, test, cue, args)
    if not args.no_conventional:
        rows += conventional_rows(train, test, args)
    _print_table(rows)
    result = {"machine": machine(), "data": source, "split": args.split, "train": len(train), "test": len(test),
              "rows": rows, "paper_pct": PAPER}
    if args.epoch_timing:
        epochs = {r["classifier"][4:]: r["epochs"] for r in rows if r["classifier"] in ("cnn-cutaneous", "cnn-kinesthetic")}
        result["projection"] = p = epoch_projection(args.epoch_timing, epochs, args.seed, args.threads)
        print(f"projection to {PAPER_TRAIN} training sequences: epoch s {p['paper_epoch_s']}, epochs {p['epochs']}"
              f" -> {p['projected_train_min']:.1f} min for the pair")
    if args.json:
        json.dump(result, sys.stdout, indent=1, default=str)
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
