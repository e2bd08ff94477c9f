"""``make demo`` / ``visuotactile demo``: the pipeline on built-in objects, as tables and figures.

What it runs grows with the toolkit: today it builds one instance of every catalogue class, measures it
(size, watertightness, curvature), draws the catalogue, attends to one object (saliency), and touches it
along blind and guided contours with the virtual FSR array, writing PNGs and a JSON summary.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from perception.atomic import write_text
from perception.geometry import ObjectModel

log = logging.getLogger(__name__)


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


def _print_table(rows: list[dict]) -> None:
    keys = list(rows[0])
    widths = [max(len(k), *(len(str(r[k])) for r in rows)) for k in keys]
    print("  ".join(k.ljust(w) for k, w in zip(keys, widths)))
    for r in rows:
        print("  ".join(str(r[k]).ljust(w) for k, w in zip(keys, widths)))


def run_demo(out: Path, seed: int = 0) -> dict:
    """Run the demo, writing figures and ``summary.json`` into ``out``; returns the summary."""
    from perception.shapes import catalogue_figure

    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"seed": seed, "figures": []}

    print("Built-in catalogue, one instance per class:")
    models, rows = _build_catalogue(seed)
    _print_table(rows)
    summary["catalogue"] = rows
    catalogue_figure(out / "catalogue.png", seed=seed, models=list(models.values()))
    summary["figures"].append("catalogue.png")

    touched = _touch(models["mug"], out, seed)
    summary["figures"] += touched.pop("figures")
    summary.update(touched)

    write_text(out / "summary.json", json.dumps(summary, indent=2))
    print(f"\nWrote {', '.join(summary['figures'])} and summary.json to {out}/")
    return summary


def _touch(model, out: Path, seed: int) -> dict:
    """Saliency on one object, then blind and guided exploration with the FSR array."""
    from perception.saliency import plot_saliency, saliency
    from tactile import explore_object, make_contour
    from tactile.figures import plot_sequence

    result: dict = {"figures": []}
    start = time.perf_counter()
    attention = saliency(model, method="multiview", seed=seed)
    result["saliency_seconds"] = round(time.perf_counter() - start, 3)
    print(f"\nSaliency of {model.name} ({attention.method}): {result['saliency_seconds']} s, "
          f"channels {', '.join(attention.channels_computed)}")
    plot_saliency(attention, out / "saliency.png", n_points=10)
    result["figures"].append("saliency.png")

    for strategy in ("blind", "guided"):
        start = time.perf_counter()
        sequences = explore_object(model, strategy=strategy, n_contours=4, seed=seed, saliency=attention)
        seconds = time.perf_counter() - start
        sides = np.concatenate([s.pad_sides_mm for s in sequences])
        print(f"{strategy:>6}: {len(sequences)} contours x {len(sequences[0].frames)} probes in {seconds:.2f} s, "
              f"pad side {sides.min():.1f}-{sides.max():.1f} mm")
        first = sequences[0]
        plot_sequence(model, make_contour(model, first.plane, first.n_probes), first, out / f"contour_{strategy}.png")
        result["figures"].append(f"contour_{strategy}.png")
        result[f"{strategy}_seconds"] = round(seconds, 3)
    return result
