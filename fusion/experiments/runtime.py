"""Recognition error against run time per decision: probes per contour, taxel grid, K touches, classifier.

For every (probes P, grid G) a store of the paper objects is generated with that sensor, and one of the same
objects each in its seeded random pose; each pose-free classifier is trained on some objects as stored and
tested on held-out ones (one instance per class when every class has at least two, else 20 % of the
sequences), upright and in any pose (the same test objects, paired). A decision touches K contours and
classifies each:

    time per decision = K x (touching one contour + inference on one sequence)

touching = cutting the contour and pressing the pad at its P probes (ray casting, measured in this process on
``TIMING_OBJECTS`` objects x ``TIMING_CONTOURS`` contours, median), inference = batch inference time per
sequence (measured where the model was trained: in a fit worker, on its one core, beside the other workers).
Guided decisions also need the object's saliency once; that time is stated separately, not added.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from fusion.experiments.analysis import name_operating_points, pareto_front, touches_score
from fusion.experiments.context import Context
from fusion.experiments.data import any_pose, ensure_store, load_models
from fusion.experiments.models import DISPLAY, digest, pick
from fusion.experiments.parallel import FitTask, StoreRows, run_tasks
from fusion.experiments.protocol import same_objects
from fusion.experiments.touch import touch_object
from perception.errors import VisuotactileError
from tactile.sampling import PAPER_STRATEGIES
from tactile.sampling import STRATEGIES as METHODS
from tactile.sensor import FSRSensor
from tactile.touching import TouchTiming

log = logging.getLogger(__name__)

TIMING_OBJECTS = 2
TIMING_CONTOURS = 5


def saliency_for(models: list, strategies, seed: int) -> tuple[dict, dict]:
    """Each guided-like strategy's saliency of ``models`` ({strategy: {name: Saliency}}) and its median
    seconds per object ({strategy: s}, 0 for blind), computed once for all (probes, grid) settings."""
    from perception.saliency import saliency

    attention, seconds = {}, {}
    for strategy in strategies:
        attention[strategy], times = {}, []
        for model in models if METHODS[strategy] else []:
            start = time.perf_counter()
            attention[strategy][model.name] = saliency(model, METHODS[strategy], seed=seed)
            times.append(time.perf_counter() - start)
        seconds[strategy] = float(np.median(times)) if times else 0.0
    return attention, seconds


def touch_seconds(models: list, probes: int, grid: int, seed: int, attention: dict,
                  strategies=PAPER_STRATEGIES) -> dict[str, float]:
    """Median seconds per contour (cut + press) of each strategy with a P-probe, G x G sensor."""
    sensor = FSRSensor(rows=grid, cols=grid)
    out = {}
    for strategy in strategies:
        timing = TouchTiming()
        for model in models:
            touch_object(model, strategy, TIMING_CONTOURS, sensor=sensor, probes=probes, seed=seed,
                         attention=attention[strategy].get(model.name), timing=timing)
        out[strategy] = timing.median_contour()
    return out


def runtime_rows(ctx: Context, objects) -> dict:
    """Points {classifier, strategy, probes, grid, k, error, seconds, error_any_pose, ...}, the Pareto front
    (upright errors) and its named operating points."""
    sizes = ctx.sizes
    by_object = min(np.unique([label for _, label in objects], return_counts=True)[1]) >= 2
    timing_models = load_models(objects[:: max(1, len(objects) // TIMING_OBJECTS)][:TIMING_OBJECTS])
    attention, saliency_seconds = saliency_for(timing_models, sizes.runtime_strategies, ctx.seed)
    # the stores and the touch timings first (nothing else runs while touches are timed), then every fit at once
    settings, tasks = [], {}
    for probes in sizes.runtime_probes:
        for grid in sizes.runtime_grids:
            sensor = FSRSensor(rows=grid, cols=grid)
            (ds, record), (any_ds, any_record) = (
                ensure_store(pose_objects, ctx.path("stores"), strategies=sizes.runtime_strategies,
                             contours=sizes.runtime_contours, seed=ctx.seed, sensor=sensor, probes=probes,
                             workers=ctx.workers, progress=ctx.progress)
                for pose_objects in (objects, any_pose(objects, ctx.seed)))
            seconds = touch_seconds(timing_models, probes, grid, ctx.seed, attention, sizes.runtime_strategies)
            for strategy in sizes.runtime_strategies:
                settings.append((probes, grid, strategy, seconds[strategy]))
                index = ds.indices(strategy)
                split = ds.split_by_object if by_object else ds.split_by_sequence
                train, test = split(1 / 3 if by_object else 0.2, seed=ctx.seed, index=index)
                folder = ctx.path("models", "runtime", f"p{probes}-g{grid}", strategy)
                train_record = {"part": "runtime", "store": digest(record), "strategy": strategy, "train": digest(train)}
                train_rows = StoreRows(str(ds.path), train)
                for name, factory in pick(ctx.classifiers, sizes.unseen_classifiers).items():
                    tasks[probes, grid, strategy, name, "test"] = FitTask(
                        name, factory, train_rows, StoreRows(str(ds.path), test), folder, train_record,
                        {"tag": "test", "test": digest(test)})
                    if by_object:
                        any_test = same_objects(ds, test, any_ds, strategy)
                        tasks[probes, grid, strategy, name, "anypose"] = FitTask(
                            name, factory, train_rows, StoreRows(str(any_ds.path), any_test), folder, train_record,
                            {"tag": "anypose", "store": digest(any_record), "test": digest(any_test)})
    outcomes = dict(zip(tasks, run_tasks(list(tasks.values()), ctx.workers, ctx.progress), strict=True))
    points, failures = [], []
    for probes, grid, strategy, per_contour in settings:
        for name in pick(ctx.classifiers, sizes.unseen_classifiers):
            pred, any_pred = (outcomes.get((probes, grid, strategy, name, tag)) for tag in ("test", "anypose"))
            failed = next((o for o in (pred, any_pred) if isinstance(o, BaseException)), None)
            if failed is not None:
                if not isinstance(failed, VisuotactileError | ValueError | RuntimeError):
                    raise failed
                log.warning("runtime P%d G%d %s %s failed: %s", probes, grid, strategy, name, failed)
                failures.append({"classifier": name, "strategy": strategy, "probes": probes, "grid": grid,
                                 "error": f"{type(failed).__name__}: {failed}"})
                continue
            per_touch = per_contour + pred.predict_seconds
            by = "object" if by_object else "decision"
            for k in sizes.touches:
                try:
                    acc = touches_score(pred, k, "log", by=by, seed=ctx.seed)
                    any_acc = None if any_pred is None else touches_score(any_pred, k, "log", by=by, seed=ctx.seed)
                except VisuotactileError:
                    continue  # fewer than k test contours per object
                points.append({
                    "classifier": DISPLAY.get(name, name), "name": name, "strategy": strategy,
                    "probes": probes, "grid": grid, "k": k, "accuracy": acc.to_dict(),
                    "error": round(1 - acc.value, 4), "seconds": k * per_touch,
                    "accuracy_any_pose": None if any_acc is None else any_acc.to_dict(),
                    "error_any_pose": None if any_acc is None else round(1 - any_acc.value, 4),
                    "touch_seconds_per_contour": per_contour,
                    "inference_seconds_per_sequence": pred.predict_seconds,
                    "saliency_seconds_per_object": saliency_seconds[strategy],
                    "fit_seconds": pred.fit_seconds})
    front = pareto_front([p["seconds"] for p in points], [p["error"] for p in points]) if points else []
    named = name_operating_points([p["seconds"] for p in points], [p["error"] for p in points], front)
    for i, p in enumerate(points):
        p["label"] = f"{p['name']} {p['strategy']} P{p['probes']} G{p['grid']} K{p['k']}"
        p["on_front"] = bool(i in {int(j) for j in front})
    return {"points": points, "front": [int(i) for i in front], "named": named, "failures": failures,
            "split": "by object (one held-out instance per class)" if by_object else "80/20 by sequence"}


__all__ = ["TIMING_CONTOURS", "TIMING_OBJECTS", "runtime_rows", "saliency_for", "touch_seconds"]
