"""Attention models compared: where the contours go (blind, multiview = the paper's guided, mesh saliency,
ISS, and PCL's Harris 3D and ISS 3D keypoints when the peer program is built), judged by recognising unseen
objects.

The strategies share one store of the paper objects, the PCL ones a second store (so building or removing
the peer program leaves the first store and its models valid); a grouped k-fold by object trains the first
unseen-objects classifier (pose-free cues) on the objects as stored and tests it upright and in any pose;
accuracy for one touch and for the largest K (sum of log probabilities), bootstrap over objects, and each
strategy's paired difference to blind contours at the largest K. Saliency time per object is measured on the
first object of each class (median; for PCL it includes starting the program and its file I/O). Without the program the PCL rows say "not built" and how to build it.
"""

from __future__ import annotations

import logging
import statistics
import time

from fusion.experiments.analysis import paired_difference, score, touches_score
from fusion.experiments.context import Context
from fusion.experiments.data import load_models
from fusion.experiments.models import DISPLAY, pick
from fusion.experiments.protocol import POSES, grouped_kfold, pose_stores
from perception.saliency import pcl_available, pcl_binary
from tactile.sampling import STRATEGIES as METHODS

log = logging.getLogger(__name__)

ATTENTION_STRATEGIES = ("blind", "guided", "mesh", "iss")
#: Strategies of the PCL keypoint peer (benchmarks/peers, built by `make peers`), run when it is built.
PCL_STRATEGIES = ("pcl_harris", "pcl_iss")
LABELS = {"pcl_harris": "PCL Harris 3D keypoints", "pcl_iss": "PCL ISS 3D keypoints"}


def saliency_seconds(models: list, seed: int, strategies=ATTENTION_STRATEGIES) -> dict[str, float]:
    """Median wall seconds of each strategy's saliency method on ``models`` (0 for blind)."""
    from perception.saliency import saliency

    out = {}
    for strategy in strategies:
        method = METHODS[strategy]
        times = []
        for model in models if method else []:
            start = time.perf_counter()
            saliency(model, method, seed=seed)
            times.append(time.perf_counter() - start)
        out[strategy] = round(statistics.median(times), 3) if times else 0.0
    return out


def attention_rows(ctx: Context, objects) -> list[dict]:
    """One row per (pose, strategy): accuracy at K = 1 and K = max, saliency seconds per object, and the
    paired difference to blind contours; the PCL rows say "not built" when the peer program is absent. The
    classifier is the first of the unseen-objects part (pose-free cues); models train on the objects as
    stored and are tested upright and in any pose (:data:`fusion.experiments.protocol.POSES`)."""
    sizes = ctx.sizes
    groups = [ATTENTION_STRATEGIES] + ([PCL_STRATEGIES] if pcl_available() else [])
    name, factory = next(iter(pick(ctx.classifiers, sizes.unseen_classifiers[:1]).items()))
    first_per_class: dict = {}
    for path, label in objects:
        first_per_class.setdefault(label, (path, label))
    timing_models = load_models(list(first_per_class.values()))
    k = max(sizes.touches)
    rows = []
    for strategies in groups:
        seconds = saliency_seconds(timing_models, ctx.seed, strategies)
        stores = {pose: pose_stores(ctx, objects, pose, strategies, sizes.attention_contours) for pose in POSES}
        by_pose = grouped_kfold(ctx, "attention", stores, strategies, {name: factory}, sizes.attention_folds)
        for pose in POSES:
            preds = {strategy: by_name[name] for strategy, by_name in by_pose[pose].items()}
            blind = preds.get("blind")
            for strategy, pred in preds.items():
                versus = (paired_difference(pred, blind, k, seed=ctx.seed)
                          if blind is not None and strategy != "blind" else None)
                rows.append({"pose": pose, "strategy": strategy,
                             "attention": LABELS.get(strategy) or METHODS[strategy] or "none (random vertices)",
                             "classifier": DISPLAY.get(name, name),
                             "accuracy_k1": score(pred, by="object", seed=ctx.seed).to_dict(),
                             "k": k, "accuracy_k": touches_score(pred, k, "log", by="object", seed=ctx.seed).to_dict(),
                             "minus_blind_k": versus,
                             "saliency_seconds_per_object": seconds[strategy]})
    if not pcl_available():
        for strategy in PCL_STRATEGIES:
            rows.append({"pose": "-", "strategy": strategy, "attention": LABELS[strategy],
                         "classifier": DISPLAY.get(name, name), "accuracy_k1": None, "k": k, "accuracy_k": None,
                         "minus_blind_k": None, "saliency_seconds_per_object": None,
                         "note": f"not built: {pcl_binary()} is absent (`make peers` builds it against libpcl-dev)"})
    return rows


__all__ = ["ATTENTION_STRATEGIES", "PCL_STRATEGIES", "attention_rows", "pcl_available", "saliency_seconds"]
