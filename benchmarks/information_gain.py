"""Information-gain benchmark: scikit-learn's ``mutual_info_classif`` against :mod:`fusion.mutual_info` on the
conventional pipeline's own features, with a check that the two give the same floats.

Features: the wavelet statistics (:class:`fusion.features.WaveletStatistics`) of a store's sequences, the input of
the pipeline's ``InfoGainSelector``, for each ``--cues`` cue; ``--sequences`` takes the first N of the strategy.
Without ``--store``, a seeded synthetic set of that size (Gaussian features, a few informative). Times are the
median wall seconds of ``--repeats`` calls on one thread (``information_gain`` runs scikit-learn's OpenMP searches
on one), and the ratio is measured in the same run.

    .venv/bin/python -m benchmarks.information_gain [--store PATH] [--strategy blind] [--sequences N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from benchmarks._common import machine, median_time


def store_features(path: str, strategy: str, cue: str, sequences: int | None) -> tuple[np.ndarray, np.ndarray]:
    """(S, F) wavelet statistics and (S,) labels of the first ``sequences`` sequences of ``strategy``."""
    from fusion.features import SequenceSeries, WaveletStatistics, n_series
    from tactile.dataset import open_dataset

    dataset = open_dataset(path)
    index = dataset.indices(strategy)[:sequences]
    batch = dataset.load(index)
    series = SequenceSeries(cue).fit_transform(batch)
    return WaveletStatistics(n_series=n_series(cue), wavelet="db2", level=3).fit_transform(series), batch.labels


def synthetic_features(sequences: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, 285) Gaussian features, a sixth shifted by the class, and (S,) labels of 8 classes."""
    rng = np.random.default_rng(seed)
    y = rng.integers(0, 8, sequences)
    X = rng.normal(size=(sequences, 285))
    X[:, :48] += 0.3 * y[:, None]
    return X, y


def compare(X: np.ndarray, y: np.ndarray, repeats: int, seed: int) -> dict:
    """Median seconds of both estimates, their ratio, and whether they are equal to the bit."""
    from sklearn.feature_selection import mutual_info_classif
    from threadpoolctl import threadpool_limits

    from fusion.mutual_info import mutual_info_continuous

    with threadpool_limits(limits=1):
        ours_s, ours = median_time(lambda: mutual_info_continuous(X, y, random_state=seed), repeats)
        sklearn_s, theirs = median_time(lambda: mutual_info_classif(X, y, random_state=seed), repeats)
    return {"sequences": len(X), "features": int(X.shape[1]), "sklearn_s": round(sklearn_s, 3),
            "ours_s": round(ours_s, 3), "ratio": round(sklearn_s / ours_s, 1),
            "equal": bool(np.array_equal(ours, theirs))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.information_gain", description=__doc__.split("\n")[0])
    parser.add_argument("--store", help="a dataset store (default: synthetic features)")
    parser.add_argument("--strategy", default="blind", help="the store's contour strategy")
    parser.add_argument("--cues", default="normals,invariant", help="kinesthetic cues, comma-separated (store only)")
    parser.add_argument("--sequences", type=int, default=None,
                        help="first N sequences of the strategy (synthetic: N, default 2,000)")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (median)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    args = parser.parse_args(argv)
    if args.sequences is not None and args.sequences < 2:
        parser.error("--sequences must be at least 2")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")

    rows = []
    if args.store:
        for cue in [c.strip() for c in args.cues.split(",") if c.strip()]:
            X, y = store_features(args.store, args.strategy, cue, args.sequences)
            rows.append({"data": f"{args.strategy}, {cue}", **compare(X, y, args.repeats, args.seed)})
    else:
        X, y = synthetic_features(args.sequences or 2000, args.seed)
        rows.append({"data": "synthetic", **compare(X, y, args.repeats, args.seed)})
    print("| data | sequences x features | scikit-learn s | ours s | ratio | same floats |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['data']} | {r['sequences']} x {r['features']} | {r['sklearn_s']} | {r['ours_s']} | "
              f"{r['ratio']} | {'yes' if r['equal'] else 'NO'} |")
    if args.json:
        json.dump({"machine": machine(), "store": args.store, "repeats": args.repeats, "rows": rows}, sys.stdout,
                  indent=1, default=str)
        print()
    return 0 if all(r["equal"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
