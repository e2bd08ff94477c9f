"""``make demo`` / ``visuotactile demo``: the toolkit end to end on built-in objects.

1. The catalogue: one instance per class, measured (size, watertightness, curvature) and drawn.
2. Attention and touch: saliency of a mug, blind and guided contours touched with the FSR array (figures).
3. Recognition, with the experiments' machinery (:mod:`fusion.experiments`): guided and blind tactile data
   of ``objects_per_class`` instances per class (:data:`DEMO_SIZES`), one instance per class held out as
   *unseen*; CNN fusion, SVM and kNN trained on 80 % of the other instances' sequences and tested on the
   remaining 20 % (the paper's by-sequence protocol) and on the unseen instances; K touches per decision on
   the unseen instances. A Table-1-style table is printed and ``report.md`` written with the figures.

Default sizes (:data:`DEMO_SIZES`, chosen for under 5 minutes on 2 CPU cores): 10 classes x 3 instances,
30 contours per object and strategy (1,800 sequences), CNN at most 12 epochs. Models are saved in ``<out>/models/`` (guided) and
``<out>/models/blind/`` for ``visuotactile recognize``; stores, models and predictions are reused by a re-run.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fusion.evaluate import PAPER_TABLE1, confusion, markdown_table, plot_confusion
from fusion.experiments.analysis import score
from fusion.experiments.config import Sizes
from fusion.experiments.data import catalogue_objects, ensure_store, split_loader
from fusion.experiments.figures import plot_touches
from fusion.experiments.models import DISPLAY, MODALITY_DISPLAY, Predictions, digest, train_and_predict
from fusion.experiments.protocol import touches_rows
from fusion.experiments.report import pct
from perception.atomic import write_text
from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel

log = logging.getLogger(__name__)


#: The demo's sizes: reproduce's unseen-objects part at demo scale. The demo reads ``objects_per_class``,
#: ``unseen_contours`` (contours per object and strategy), ``epochs``, ``touches``, ``unseen_classifiers`` and
#: ``strategies``.
DEMO_SIZES = Sizes(unseen_contours=30, epochs=12)


def check_demo_sizes(sizes: Sizes) -> Sizes:
    """``sizes`` if the demo can run with them.

    Raises:
        InvalidArgumentError: fewer than 2 objects per class (one is held out as unseen), or fewer contours per
            object than the largest K.
    """
    if sizes.objects_per_class < 2:
        raise InvalidArgumentError(
            f"the demo needs at least 2 objects per class (one is held out as unseen), got {sizes.objects_per_class}")
    if sizes.unseen_contours < max(sizes.touches):
        raise InvalidArgumentError(
            f"contours ({sizes.unseen_contours}) must be at least the largest K {max(sizes.touches)}")
    return sizes


def _build_catalogue(seed: int) -> tuple[dict[str, ObjectModel], list[dict]]:
    """One instance per class, and a table row per instance (build and curvature time included)."""
    from perception.shapes import CLASSES, make_object

    models, rows = {}, []
    for name in CLASSES:
        start = time.perf_counter()
        model = models[name] = make_object(name, seed)
        curvature = model.curvature
        rows.append(
            {
                "class": name,
                "vertices": model.n_vertices,
                "triangles": model.n_triangles,
                "watertight": bool(model.is_watertight),
                "diagonal_mm": round(model.diagonal, 3),
                "area_cm2": round(float(model.triangle_areas.sum()) / 100.0, 2),
                "median_abs_mean_curvature_per_m": round(float(np.median(np.abs(curvature.mean))) * 1000, 2),
                "seconds": round(time.perf_counter() - start, 3),
            }
        )
    return models, rows


def format_table(rows: list[dict]) -> str:
    """Rows as aligned plain-text columns."""
    keys = list(rows[0])
    widths = [max(len(k), *(len(str(r[k])) for r in rows)) for k in keys]
    lines = ["  ".join(k.ljust(w) for k, w in zip(keys, widths))]
    lines += ["  ".join(str(r[k]).ljust(w) for k, w in zip(keys, widths)) for r in rows]
    return "\n".join(lines)


def run_demo(out: Path, seed: int = 0, *, sizes: Sizes = DEMO_SIZES, classifiers: dict | None = None,
             recognition: bool = True, workers: int | None = None, progress: bool = True,
             echo: Callable[[str], None] = print) -> dict:
    """Run the demo, writing figures, ``report.md`` and ``summary.json`` into ``out``; returns the summary.

    Args:
        echo: where the tables and messages go (the CLI's stdout, or stderr under ``--json``).
        classifiers: name -> factory of an unfitted classifier (default: the toolkit's, see ``sizes``).
        recognition: run the recognition part (3. in the module docstring).
    """
    from perception.shapes import catalogue_figure

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"seed": seed, "figures": []}

    echo("Built-in catalogue, one instance per class:")
    models, rows = _build_catalogue(seed)
    echo(format_table(rows))
    summary["catalogue"] = rows
    catalogue_figure(out / "catalogue.png", seed=seed, models=list(models.values()))
    summary["figures"].append("catalogue.png")

    touched = _touch(models["mug"], out, seed, echo)
    summary["figures"] += touched.pop("figures")
    summary.update(touched)

    if recognition:
        result = run_recognition(out, seed, sizes, classifiers, workers=workers, progress=progress,
                           classes=list(models), echo=echo)
        summary["figures"] += result.pop("figures")
        summary["recognition"] = result
        if (out / "models" / "svm.vtm").is_file():  # one active-touch episode with the trained SVM
            from fusion.active.figure import demo_episode
            from fusion.base import load_model

            summary["active"] = demo_episode(out, load_model(out / "models" / "svm.vtm"),
                                             instance_seed=seed + sizes.objects_per_class, seed=seed)
            summary["figures"].append(summary["active"]["figure"])
            echo(f"\nActive touch, {summary['active']['object']} (unseen), information policy: decisions "
                 f"{summary['active']['decisions']} ({summary['active']['seconds']} s)")
    write_text(out / "summary.json", json.dumps(summary, indent=2, default=str))
    write_text(out / "report.md", _report(summary))
    echo(f"\nWrote report.md, summary.json and {len(summary['figures'])} figures to {out}/")
    return summary


def _touch(model, out: Path, seed: int, echo: Callable[[str], None] = print) -> dict:
    """Saliency on one object, then blind and guided exploration with the FSR array."""
    from perception.saliency import plot_saliency, saliency
    from tactile import make_contour, touch
    from tactile.figures import plot_sequence

    result: dict = {"figures": []}
    start = time.perf_counter()
    attention = saliency(model, method="multiview", seed=seed)
    result["saliency_seconds"] = round(time.perf_counter() - start, 3)
    echo(f"\nSaliency of {model.name} ({attention.method}): {result['saliency_seconds']} s, "
          f"channels {', '.join(attention.channels_computed)}")
    plot_saliency(attention, out / "saliency.png", n_points=10)
    result["figures"].append("saliency.png")

    for strategy in ("blind", "guided"):
        start = time.perf_counter()
        sequences = touch(model, strategy, 4, seed=seed, saliency=attention)
        seconds = time.perf_counter() - start
        sides = np.concatenate([s.pad_sides_mm for s in sequences])
        echo(f"{strategy:>6}: {len(sequences)} contours x {len(sequences[0].frames)} probes in {seconds:.2f} s, "
              f"pad side {sides.min():.1f}-{sides.max():.1f} mm")
        first = sequences[0]
        plot_sequence(model, make_contour(model, first.plane, first.n_probes), first, out / f"contour_{strategy}.png")
        result["figures"].append(f"contour_{strategy}.png")
        result[f"{strategy}_seconds"] = round(seconds, 3)
    return result


def _default_classifiers(sizes: Sizes, seed: int, progress: bool) -> dict:
    from fusion.experiments.models import default_classifiers

    every = default_classifiers(seed, sizes.epochs, progress=progress)
    return {name: every[name] for name in sizes.unseen_classifiers}


def run_recognition(out: Path, seed: int, sizes: Sizes, classifiers: dict | None, *, classes,
              workers: int | None = None, progress: bool = True, echo: Callable[[str], None] = print) -> dict:
    """The recognition part: data, training, tests by sequence and on unseen instances, K touches, figures.

    Raises:
        InvalidArgumentError: sizes the demo cannot run with (:func:`check_demo_sizes`).
    """
    check_demo_sizes(sizes)
    classifiers = classifiers or _default_classifiers(sizes, seed, progress)
    start = time.perf_counter()
    objects = catalogue_objects(classes, sizes.objects_per_class, first_seed=seed)
    echo(f"\nRecognition: {len(objects)} objects ({sizes.objects_per_class} per class), {sizes.unseen_contours} contours "
          "per object and strategy")
    ds, record = ensure_store(objects, out / "stores", strategies=sizes.strategies, contours=sizes.unseen_contours,
                      seed=seed, workers=workers, progress=progress)
    data_seconds = time.perf_counter() - start
    preds: dict[str, dict[str, dict[str, Predictions]]] = {"sequence": {}, "unseen": {}}
    loaders = {}  # per strategy: the training sequences and the unseen instances' ones
    for strategy in sizes.strategies:
        index = ds.indices(strategy)
        seen, unseen = ds.split_by_object(1 / sizes.objects_per_class, seed=seed, index=index)
        train, test = ds.split_by_sequence(0.2, seed=seed, index=seen)
        batch = split_loader(ds, train, test)
        unseen_batch = split_loader(ds, train, unseen)
        loaders[strategy] = unseen_batch
        folder = out / "models" if strategy == "guided" else out / "models" / strategy
        train_record = {"part": "demo", "store": digest(record), "strategy": strategy, "train": digest(train)}
        for name, factory in classifiers.items():
            echo(f"  {strategy}: training {DISPLAY.get(name, name)} on {len(train)} sequences")
            preds["sequence"].setdefault(strategy, {})[name] = train_and_predict(
                name, factory, lambda b=batch: b("train"), lambda b=batch: b("test"), folder, train_record,
                {"tag": "sequence", "test": digest(test)})
            preds["unseen"].setdefault(strategy, {})[name] = train_and_predict(
                name, factory, lambda b=batch: b("train"), lambda b=unseen_batch: b("test"), folder, train_record,
                {"tag": "unseen", "test": digest(unseen)})
    table = _table(preds, seed)
    echo("\nTest accuracy, 95 % bootstrap interval (by sequence: over sequences; unseen: over objects):")
    echo(format_table(table))
    touches = touches_rows(preds["unseen"], "unseen_instances", sizes.touches, seed)
    figures = [plot_touches(touches, out / "accuracy_vs_k.png").name]
    for strategy in sizes.strategies:
        for name, pred in preds["unseen"][strategy].items():
            file = out / f"confusion_unseen_{strategy}_{name}.png"
            plot_confusion(confusion(pred.labels, pred.predicted, pred.classes), pred.classes, file,
                           title=f"{DISPLAY.get(name, name)}, {strategy}, unseen instances")
            figures.append(file.name)
    k_best = max(sizes.touches)
    name = "knn" if "knn" in classifiers else next(iter(classifiers))  # kNN: calibrating it takes seconds
    strategy = sizes.strategies[-1]
    calibration = run_calibration(out, name, classifiers[name], loaders[strategy], strategy, k_best, seed, echo)
    if calibration:
        figures.append(calibration["figure"])
    k_rows = [r for r in touches if r["k"] == k_best and r["rule"] == "log"]
    echo(f"\nUnseen instances, K = {k_best} touches per decision (sum of log probabilities):")
    for r in k_rows:
        echo(f"  {r['classifier']:<16} {r['strategy']:<7} {pct(r['accuracy'])}")
    demo_sizes = {"objects_per_class": sizes.objects_per_class, "contours": sizes.unseen_contours,
                  "epochs": sizes.epochs, "touches": list(sizes.touches),
                  "classifiers": list(sizes.unseen_classifiers), "strategies": list(sizes.strategies)}
    return {"sizes": {**demo_sizes, "classes": list(classes)}, "objects": [f"{c}/{s}" for c, s in objects],
            "table": table, "touches": touches, "calibration": calibration, "figures": figures,
            "data_seconds": round(data_seconds, 1),
            "seconds": round(time.perf_counter() - start, 1),
            "models": sorted(str(p.relative_to(out)) for p in (out / "models").rglob("*.vtm"))}


def run_calibration(out: Path, name: str, factory, load, strategy: str, k: int, seed: int,
                    echo: Callable[[str], None] = print) -> dict:
    """Calibrate classifier ``name`` on the seen instances' ``strategy`` sequences (:func:`fusion.openset.calibrate`,
    two folds by object, no open set: a class may have only two seen instances) and compare its unseen instances'
    decisions before (raw, log rule) and after, at 1 and ``k`` touches: ECE with 95 % intervals over objects and a
    reliability diagram (``reliability.png``).

    Returns:
        {"classifier", "strategy", "temperature", "dependence", "rows": [{"k", "variant", "ece", "low", "high",
        "n"}], "figure"}, or None (said through ``echo``) when a class has fewer than two seen instances.
    """
    from fusion.calibration import ece_interval, plot_reliability, reliability
    from fusion.decide import touch_groups
    from fusion.experiments.openset import VARIANTS, class_index
    from fusion.openset import calibrate, objects_per_class

    train = load("train")
    if min(objects_per_class(train).values()) < 2:
        echo("\nCalibration skipped: it holds seen instances out, and a class has only one")
        return None
    model = calibrate(factory(), train, cv=2, open_set=False, max_touches=k, random_state=seed)
    batch = load("test")
    raw = model.predict_proba_uncalibrated(batch)
    y = class_index(model, batch)
    fuse = {"before": VARIANTS["before (raw, log rule)"], "after": VARIANTS["after (+ confidence map for K)"]}
    rows, curves = [], {}
    for touches in sorted({1, k}):
        groups = touch_groups(batch.object_ids, touches, seed=seed)
        first = groups[:, 0]
        for variant, rule in fuse.items():
            fused = rule(model.calibration_, raw[groups])
            rows.append({"k": touches, "variant": variant,
                         **ece_interval(fused, y[first], batch.object_ids[first], seed=seed)})
            curves[f"K={touches}, {variant}"] = reliability(fused, y[first])
    label = DISPLAY.get(name, name)
    plot_reliability(curves, out / "reliability.png", title=f"{label}, {strategy}, unseen instances")
    echo(f"\nCalibration of {label} ({strategy}; fitted on the seen instances only), ECE on the unseen ones:")
    for r in rows:
        echo(f"  K = {r['k']:<2} {r['variant']:<7} {r['ece']:.3f} [{r['low']:.3f}, {r['high']:.3f}]")
    state = model.calibration_
    return {"classifier": label, "strategy": strategy, "temperature": round(float(state["temperature"]), 4),
            "dependence": round(float(state["dependence"]), 4), "rows": rows, "figure": "reliability.png"}


def _table(preds: dict, seed: int) -> list[dict]:
    rows = []
    strategies = list(preds["sequence"])
    names = list(preds["sequence"][strategies[0]])
    for name in names:
        variants = [(DISPLAY.get(name, name), None)]
        if name == "cnn":
            variants += [(label, m) for m, label in MODALITY_DISPLAY.items()
                         if m in preds["sequence"][strategies[0]][name].modalities]
        for label, modality in variants:
            row = {"classifier": label}
            for split, by in (("sequence", "decision"), ("unseen", "object")):
                for strategy in strategies:
                    pred = preds[split][strategy][name]
                    pred = pred.modality(modality) if modality else pred
                    row[f"{split} {strategy}"] = pct(score(pred, by=by, seed=seed).to_dict())
            paper = PAPER_TABLE1.get(name) if modality is None else None
            row["paper guided / blind"] = f"{paper[0]:.2f} / {paper[1]:.2f} %" if paper else "-"
            rows.append(row)
    return rows


def _report(summary: dict) -> str:
    lines = ["# visuotactile demo", "", (f"Seed {summary['seed']}. Saliency of one mug: "
             f"{summary['saliency_seconds']} s."), "", "![catalogue](catalogue.png)", "",
             "![saliency](saliency.png)", "", "![guided contour](contour_guided.png)", "",
             "![blind contour](contour_blind.png)", ""]
    rec = summary.get("recognition")
    if rec:
        s = rec["sizes"]
        lines += ["## Recognition", "",
                  (f"{len(rec['objects'])} built-in objects ({s['objects_per_class']} per class, one per class "
                   f"held out as unseen), {s['contours']} contours per object and strategy, CNN at most "
                   f"{s['epochs']} epochs. By sequence: 80 % of the seen instances' sequences train, 20 % test "
                   "(the paper's protocol; interval over sequences). Unseen: the held-out instances "
                   "(interval over objects). 95 % percentile bootstrap, 1000 resamples."), "",
                  markdown_table(rec["table"]), "", "![accuracy vs K](accuracy_vs_k.png)", ""]
        lines += [f"![{f}]({f})" for f in summary["figures"] if f.startswith("confusion")]
        cal = rec["calibration"]
        lines += [] if not cal else ["", "### Calibration", "", (f"{cal['classifier']} ({cal['strategy']}), calibrated on the seen "
                  f"instances only (temperature {cal['temperature']:g}, touch dependence {cal['dependence']:g}); "
                  "ECE of the unseen instances' decisions [95 % interval over objects]: "
                  + "; ".join(f"K = {r['k']} {r['variant']} {r['ece']:.3f} [{r['low']:.3f}, {r['high']:.3f}]"
                              for r in cal["rows"])), "", "![reliability](reliability.png)"]
        lines += ["", f"Recognition took {rec['seconds']} s (data {rec['data_seconds']} s). Models: "
                  + ", ".join(f"`{m}`" for m in rec["models"]), ""]
    act = summary.get("active")
    if act:
        lines += ["## Active touch", "", (f"{act['object']} (an instance nobody trained on), its visual model a 1 mm "
                  "noisy copy; the information policy plans each touch on it (simulated touches of 12 candidate "
                  "contours), the SVM reads the real touch, the log rule fuses. Probability of the true class after "
                  "each touch: " + ", ".join(f"{p:.2f}" for p in act["posterior_true"])
                  + f" ({act['seconds']} s)."), "", "![active episode](active_episode.png)", ""]
    return "\n".join(lines)


__all__ = ["DEMO_SIZES", "check_demo_sizes", "format_table", "run_calibration", "run_demo", "run_recognition"]
