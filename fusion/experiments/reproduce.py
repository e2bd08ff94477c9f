"""``reproduce``: the paper's protocol on a class-per-folder mesh set and the parts beyond it, as a report folder.

Parts (each can be chosen with ``parts``): ``paper`` (Table 1), ``unseen`` (grouped k-fold by object over all
instances, each test object upright and in a seeded random pose, with paired guided-vs-blind and upright-vs-any-
pose differences over objects), ``touches`` (K per decision, on the paper and unseen predictions), ``noise``, ``attention`` and
``runtime`` (error vs time, Pareto front), ``calibration`` (ECE at K touches before / after calibration fitted
inside the training folds, reliability diagrams) and ``openset`` (classes rotated out of training: AUROC known vs
unknown, share of unknown objects rejected; :mod:`fusion.experiments.openset`). ``touches`` needs ``paper`` (it reuses its predictions), ``noise``
needs ``unseen`` (it reuses its fold models on their test objects, in any pose). ``active`` (random / saliency / information touch policies on the unseen objects in any pose, :mod:`fusion.experiments.active`) runs only when named. Everything expensive is cached under the report folder (stores, models, predictions, part
results), so an interrupted run resumes and the same seed gives the same numbers. Models train side by side, one
worker process per core (:mod:`fusion.experiments.parallel`).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from fusion.experiments import figures
from fusion.experiments.config import FULL, NOISE_KINDS, QUICK, Sizes
from fusion.experiments.context import Context
from fusion.experiments.data import folder_objects
from fusion.experiments.models import default_classifiers
from fusion.experiments.parallel import shared_workers
from fusion.experiments.protocol import (
    accuracy_rows,
    confusion_figures,
    paper_protocol,
    pose_differences,
    strategy_differences,
    touches_rows,
    unseen_objects,
)
from fusion.experiments.report import render
from perception.atomic import write_text
from perception.errors import InvalidArgumentError, VisuotactileError
from perception.runtime import machine_line as machine

log = logging.getLogger(__name__)

PARTS = ("paper", "unseen", "touches", "noise", "attention", "runtime", "calibration", "openset", "active")
#: What runs when no parts are named: all but calibration, open set and active touch (each trains or plays many
#: models and episodes; ask by name).
DEFAULT_PARTS = PARTS[:6]
BOOTSTRAP_NOTE = ("over test sequences for the paper protocol; over objects (whole objects resampled) "
                  "for unseen objects, K touches, noise, attention and the run-time part; differences (guided - blind, "
                  "any pose - upright) are paired object by object and bootstrapped over objects.")


def reproduce(
    data: str | Path,
    out: str | Path,
    *,
    classes=None,
    objects_per_class: int | None = None,
    quick: bool = False,
    seed: int = 0,
    parts=DEFAULT_PARTS,
    sizes: Sizes | None = None,
    classifiers: dict | None = None,
    workers: int | None = None,
    progress: bool = True,
    command: str | None = None,
    outliers=None,
) -> dict:
    """Run the experiments on the mesh set ``data`` and write the report folder ``out``; returns the results.

    Args:
        classes: classes to use (default: the first ``sizes.paper_classes`` for the paper-protocol parts, all
            for the unseen-objects part).
        objects_per_class: paper-protocol instances per class (default ``sizes.objects_per_class``).
        quick: the :data:`QUICK` sizes instead of :data:`FULL` (ignored when ``sizes`` is given).
        parts: which parts to run (see the module docstring).
        workers: worker processes of store generation and of model fits (None: the usable cores). The stores and
            the CNN models are the same bytes with any count (each CNN trains on one thread); the paper's SVM may
            differ in the ninth decimal (its linear algebra runs on each worker's share of the cores).
        classifiers: name -> factory (default :func:`default_classifiers`).
        outliers: objects of no class in ``data`` ((mesh path, label) or (catalogue class, seed) pairs): the
            calibration and open-set parts' CNNs also train on their touches with outlier exposure (:class:`fusion.cnn.CNNClassifier`).

    Raises:
        DatasetError: a bad data folder, unknown class, or too few instances.
        InvalidArgumentError: an unknown part, ``touches`` without ``paper`` or ``unseen``, ``noise`` without
            ``unseen``, or ``workers`` not a positive integer.
    """
    parts = tuple(parts)
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise InvalidArgumentError(f"unknown parts {unknown}; choose from {', '.join(PARTS)}")
    if "touches" in parts and not {"paper", "unseen"} & set(parts):
        raise InvalidArgumentError("the touches part reuses the paper and unseen-objects predictions: add 'paper' "
                                   "or 'unseen' to parts")
    if "noise" in parts and "unseen" not in parts:
        raise InvalidArgumentError("the noise part reuses the unseen-objects models: add 'unseen' to parts")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InvalidArgumentError(f"workers must be a positive integer or None (the usable cores), got {workers!r}")
    sizes = sizes or (QUICK if quick else FULL)
    if objects_per_class is not None:
        sizes = sizes.with_(objects_per_class=int(objects_per_class))
    out = Path(out)
    ctx = Context(out, int(seed), sizes,
                  classifiers or default_classifiers(seed, sizes.epochs, progress=progress, threads=1),
                  progress=progress, workers=workers, outliers=list(outliers) if outliers else None)
    # the paper's objects, for the parts that use them (a folder with fewer instances can still run the others)
    paper_objects = (folder_objects(data, classes, sizes.objects_per_class, max_classes=sizes.paper_classes)
                     if {"paper", "attention", "runtime"} & set(parts) else [])
    results: dict = {
        "title": "visuotactile reproduce", "command": command or " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "data": str(data), "seed": ctx.seed, "quick": quick, "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(), "bootstrap": BOOTSTRAP_NOTE, "sizes": sizes.to_dict(), "seconds": ctx.timings,
    }

    with shared_workers():  # the fit workers start once for every part
        return _run_parts(ctx, data, out, classes, sizes, parts, paper_objects, results)


def _run_parts(ctx, data, out, classes, sizes, parts, paper_objects, results) -> dict:
    """The parts of :func:`reproduce` (its arguments checked), each written to ``out`` as it finishes."""
    def timed(name, fn):
        start = time.perf_counter()
        value = fn()
        ctx.timings[name] = round(time.perf_counter() - start, 1)
        return value

    paper_preds = unseen_preds = anypose_preds = None
    if "paper" in parts:
        paper_preds = timed("paper", lambda: paper_protocol(ctx, paper_objects))
        results["paper"] = {
            "objects": [f"{label}/{Path(p).stem}" for p, label in paper_objects],
            "classes": list(dict.fromkeys(label for _, label in paper_objects)),
            "contours": sizes.paper_contours, "test_fraction": sizes.test_fraction,
            "rows": accuracy_rows(paper_preds, "decision", ctx.seed),
            "figures": confusion_figures(ctx, paper_preds, "paper"),
        }
        _write(out, results)  # a partial report after every part
    if "unseen" in parts:
        unseen_list = folder_objects(data, classes, sizes.unseen_per_class)
        by_pose = timed("unseen", lambda: unseen_objects(ctx, unseen_list))
        unseen_preds, anypose_preds = by_pose["upright"], by_pose["any pose"]
        results["unseen"] = {
            "n_objects": len(unseen_list), "classes": list(dict.fromkeys(label for _, label in unseen_list)),
            "contours": sizes.unseen_contours, "folds": sizes.unseen_folds,
            "train_contours": sizes.unseen_train_contours or sizes.unseen_contours,
            "rows": accuracy_rows(unseen_preds, "object", ctx.seed),
            "any_pose_rows": accuracy_rows(anypose_preds, "object", ctx.seed),
            "strategy_differences": strategy_differences(by_pose, sizes.touches, ctx.seed),
            "pose_differences": pose_differences(by_pose, sizes.touches, ctx.seed),
            "figures": confusion_figures(ctx, unseen_preds, "unseen")
            + confusion_figures(ctx, anypose_preds, "unseen_any_pose"),
        }
        _write(out, results)  # a partial report after every part
    if "touches" in parts:
        rows = touches_rows(paper_preds, "paper_protocol", sizes.touches, ctx.seed) if paper_preds else []
        if unseen_preds:
            rows += touches_rows(unseen_preds, "unseen_objects", sizes.touches, ctx.seed)
            rows += touches_rows(anypose_preds, "unseen_objects_any_pose", sizes.touches, ctx.seed)
        figures.plot_touches(rows, out / "accuracy_vs_k.png")
        results["touches"] = {"rows": rows, "figure": "accuracy_vs_k.png"}
        _write(out, results)  # a partial report after every part
    if "noise" in parts:
        from fusion.experiments.robustness import NOISE_POSES, noise_rows

        unseen_list = folder_objects(data, classes, sizes.unseen_per_class)
        record = {"objects": [str(p) for p, _ in unseen_list], "sizes": sizes.to_dict(), "seed": ctx.seed,
                  "models": _model_records(out), "poses": list(NOISE_POSES)}
        rows = timed("noise", lambda: ctx.cached_part("noise", record, lambda: {"rows": noise_rows(ctx, unseen_list)}))[
            "rows"]
        figures.plot_noise(rows, NOISE_KINDS, out / "accuracy_vs_noise.png")
        results["noise"] = {"rows": rows, "contours": sizes.noise_contours, "kinds": NOISE_KINDS,
                            "figure": "accuracy_vs_noise.png"}
        _write(out, results)  # a partial report after every part
    if "attention" in parts:
        from fusion.experiments.attention import attention_rows, pcl_available

        record = {"objects": [str(p) for p, _ in paper_objects], "sizes": sizes.to_dict(), "seed": ctx.seed,
                  "classifier": _describe_first(ctx, sizes), "pcl": pcl_available()}
        rows = timed("attention", lambda: ctx.cached_part("attention", record, lambda: {
            "rows": attention_rows(ctx, paper_objects)}))["rows"]
        results["attention"] = {"rows": rows, "contours": sizes.attention_contours, "folds": sizes.attention_folds}
        _write(out, results)  # a partial report after every part
    if "runtime" in parts:
        from fusion.experiments.runtime import runtime_rows

        record = {"objects": [str(p) for p, _ in paper_objects], "sizes": sizes.to_dict(), "seed": ctx.seed,
                  "classifiers": [_describe(ctx, n) for n in sizes.unseen_classifiers], "poses": 2}
        result = timed("runtime", lambda: ctx.cached_part("runtime", record, lambda: runtime_rows(ctx, paper_objects)))
        figures.plot_pareto(result, out / "pareto.png")
        results["runtime"] = {**result, "contours": sizes.runtime_contours, "figure": "pareto.png"}
        _write(out, results)  # a partial report after every part
    calibrating = [part for part in ("calibration", "openset") if part in parts]
    if calibrating:
        from fusion.experiments import openset as experiment

        unseen_list = folder_objects(data, classes, sizes.unseen_per_class)
        record = {"objects": [str(p) for p, _ in unseen_list], "sizes": sizes.to_dict(), "seed": ctx.seed,
                  "classifiers": [_describe(ctx, n) for n in sizes.calibration_classifiers]}
        if ctx.outliers:  # a run without them keeps the record (and the cached parts) it had
            record["outliers"] = [[str(x) for x in o] for o in ctx.outliers]
        records = {part: record | ({"contrastive": experiment.OPENSET_CONTRASTIVE} if part == "openset" else {})
                   for part in calibrating}  # the open-set part's CNNs alone train with the term
        todo = [part for part in calibrating if not ctx.has_part(part, records[part])]
        if len(todo) > 1:  # both parts' calibrations in one pool: they pack on the workers better than part by part
            try:
                timed("calibrations", lambda: experiment.calibrate_parts(ctx, unseen_list, todo))
            except VisuotactileError as exc:  # each part below meets it again, in turn, after the others are written
                log.warning("calibrating both parts together failed (%s); each part calibrates on its own", exc)
    for part in calibrating:
        compute = getattr(experiment, f"{part}_part")
        def run_part(part=part, record=records[part], compute=compute, objects=unseen_list):
            return ctx.cached_part(part, record, lambda: compute(ctx, objects))

        results[part] = timed(part, run_part)
        results[part] |= {"n_objects": len(unseen_list), "contours": sizes.unseen_contours,
                          "outliers": len(ctx.outliers or [])}
        if part == "openset":
            results[part]["contrastive"] = experiment.OPENSET_CONTRASTIVE
        _write(out, results)
    if "active" in parts:
        from fusion.experiments.active import active_part

        unseen_list = folder_objects(data, classes, sizes.unseen_per_class)
        results["active"] = timed("active", lambda: active_part(ctx, unseen_list, **sizes.active_options()))
        _write(out, results)
    _write(out, results)
    return results


def _describe(ctx: Context, name: str) -> str:
    from fusion.experiments.models import describe

    return describe(ctx.classifiers[name]())


def _describe_first(ctx: Context, sizes: Sizes) -> str:
    return _describe(ctx, sizes.unseen_classifiers[0])


def _model_records(out: Path) -> dict:
    """The cache records of the unseen-objects models (the noise part is redone when they change)."""
    records = {}
    for path in sorted((out / "models" / "unseen").glob("*/*/*.json")):
        try:
            records[str(path.relative_to(out))] = json.loads(path.read_text())["record"]
        except (OSError, ValueError, KeyError):
            continue
    return records


def _write(out: Path, results: dict) -> None:
    write_text(out / "results.json", json.dumps(results, indent=2, default=str))
    write_text(out / "report.md", render(results))


__all__ = ["DEFAULT_PARTS", "PARTS", "reproduce"]
