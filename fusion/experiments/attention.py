"""Attention models compared: where the contours go (blind, multiview = the paper's guided, mesh saliency,
ISS, and PCL's keypoints when the peer program is built), judged by recognising unseen objects.

Each strategy gets its own store of the paper objects; a grouped k-fold by object trains the first paper
classifier; accuracy for one touch and for the largest K (sum of log probabilities), bootstrap over objects.
Saliency time per object is measured on the first object of each class (median).
"""

from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path

from fusion.experiments.analysis import score, touches_score
from fusion.experiments.context import Context
from fusion.experiments.data import ensure_store, load_models
from fusion.experiments.models import DISPLAY, Predictions, digest, pick, train_and_predict
from fusion.experiments.protocol import _loader
from tactile.sampling import STRATEGIES as METHODS

log = logging.getLogger(__name__)

ATTENTION_STRATEGIES = ("blind", "guided", "mesh", "iss")
#: The PCL keypoint peer (benchmarks/peers, built by `make peers`).
PCL_BINARY = Path(__file__).resolve().parents[2] / "benchmarks" / "peers" / "pcl_keypoints"


def saliency_seconds(models: list, seed: int) -> dict[str, float]:
    """Median wall seconds of each strategy's saliency method on ``models`` (0 for blind)."""
    from perception.saliency import saliency

    out = {}
    for strategy in ATTENTION_STRATEGIES:
        method = METHODS[strategy]
        times = []
        for model in models if method else []:
            start = time.perf_counter()
            saliency(model, method, seed=seed)
            times.append(time.perf_counter() - start)
        out[strategy] = round(statistics.median(times), 3) if times else 0.0
    return out


def attention_rows(ctx: Context, objects) -> list[dict]:
    """One row per strategy: accuracy at K = 1 and K = max, saliency seconds per object; a PCL row."""
    sizes = ctx.sizes
    ds, record = ensure_store(objects, ctx.path("stores"), strategies=ATTENTION_STRATEGIES,
                      contours=sizes.attention_contours, seed=ctx.seed, workers=ctx.workers, progress=ctx.progress)
    name, factory = next(iter(pick(ctx.classifiers, sizes.paper_classifiers[:1]).items()))
    first_per_class: dict = {}
    for path, label in objects:
        first_per_class.setdefault(label, (path, label))
    seconds = saliency_seconds(load_models(list(first_per_class.values())), ctx.seed)
    k = max(sizes.touches)
    rows = []
    for strategy in ATTENTION_STRATEGIES:
        folds = ds.kfold_by_object(sizes.attention_folds, seed=ctx.seed, index=ds.indices(strategy))
        parts = []
        for i, (train, test) in enumerate(folds):
            batch = _loader(ds, train, test)
            parts.append(train_and_predict(
                name, factory, lambda b=batch: b("train"), lambda b=batch: b("test"),
                ctx.path("models", "attention", strategy, f"fold{i + 1}"),
                {"part": "attention", "store": digest(record), "strategy": strategy, "train": digest(train)},
                {"tag": "test", "test": digest(test)}))
        pred = Predictions.concatenate(parts)
        rows.append({"strategy": strategy, "attention": METHODS[strategy] or "none (random vertices)",
                     "classifier": DISPLAY.get(name, name),
                     "accuracy_k1": score(pred, by="object", seed=ctx.seed).to_dict(),
                     "k": k, "accuracy_k": touches_score(pred, k, "log", by="object", seed=ctx.seed).to_dict(),
                     "saliency_seconds_per_object": seconds[strategy]})
    for detector in ("harris", "iss"):
        rows.append({"strategy": f"pcl_{detector}", "attention": f"PCL {detector} keypoints",
                     "classifier": DISPLAY.get(name, name), "accuracy_k1": None, "k": k, "accuracy_k": None,
                     "saliency_seconds_per_object": None,
                     "note": (f"not run: {PCL_BINARY} is built, but contours from its keypoints are not wired "
                              "into the stores yet" if PCL_BINARY.exists() else
                              f"not built: {PCL_BINARY} is absent (`make peers` builds it against libpcl-dev)")})
    return rows


__all__ = ["ATTENTION_STRATEGIES", "PCL_BINARY", "attention_rows", "saliency_seconds"]
