"""Error against run time of vertex normals and curvature estimators on analytic surfaces.

Every normal method of :data:`perception.curvature.NORMAL_METHODS` and every curvature method of
:data:`perception.curvature.CURVATURE_METHODS` runs on a sphere (R = 50 mm), an ellipsoid (60, 40, 30 mm), a
torus (50 / 20 mm) and a closed cylinder (R = 30 mm, h = 100 mm), each at four resolutions, against the
exact answers of :mod:`perception.primitives`.

Errors: normal = angle to the analytic normal (degrees); mean curvature = |H - H_true| / max |H_true| (%);
Gaussian = |K - K_true| / max |K_true| (%), where K_true is zero everywhere (the cylinder) the scale is the
largest squared principal curvature, 1 / R^2. On the cylinder only side vertices farther than two grid
spacings from the cap rims are measured, because the rims are sharp edges, not smooth surface.

Times are medians of ``--repeats`` runs; curvature runs on a fresh ``ObjectModel`` each time (so cached
normals do not hide their cost) and includes the vertex normals it needs. The convergence table gives the
observed order p of the mean error, err ~ h^p with spacing h ~ V^(-1/2), fitted over the resolutions.

    .venv/bin/python -m benchmarks.geometry [--quick] [--json] [--repeats N]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
from tqdm import tqdm

from benchmarks._common import machine, median_time
from perception import primitives
from perception.curvature import CURVATURE_METHODS, NORMAL_METHODS, quiet_stdout, vertex_normals
from perception.geometry import ObjectModel

SPHERE_R_MM = 50.0
ELLIPSOID_AXES_MM = (60.0, 40.0, 30.0)
TORUS_MM = (50.0, 20.0)  # major, minor
CYLINDER_MM = (30.0, 100.0)  # radius, height
GRIDS = ((32, 16), (64, 32), (128, 64), (256, 128))  # torus / cylinder grids, doubling
# Below these the error is round-off, not discretisation: arccos near 1 resolves about 1e-6 degrees.
NORMAL_FLOOR_DEG = 1e-5
CURVATURE_FLOOR_PCT = 1e-4


@dataclass(frozen=True)
class Truth:
    """Analytic answers at the vertices, and which vertices are measured."""

    normals: np.ndarray
    mean: np.ndarray
    gaussian: np.ndarray
    measured: np.ndarray  # bool (V,)
    gaussian_scale: float  # 1/mm^2, the denominator of the relative Gaussian error


def _truth(normals, mean, gaussian, measured=None) -> Truth:
    measured = np.ones(len(mean), bool) if measured is None else measured
    k_max = np.abs(mean) + np.sqrt(np.maximum(mean**2 - gaussian, 0.0))
    scale = float(np.abs(gaussian[measured]).max())
    if scale == 0.0:  # flat in one direction everywhere (cylinder): use the largest k^2
        scale = float((k_max[measured] ** 2).max())
    return Truth(normals, mean, gaussian, measured, scale)


def _sphere_truth(model: ObjectModel) -> Truth:
    return _truth(*primitives.analytic_sphere(model.vertices, SPHERE_R_MM))


def _ellipsoid_truth(model: ObjectModel) -> Truth:
    return _truth(*primitives.analytic_ellipsoid(model.vertices, ELLIPSOID_AXES_MM))


def _torus_truth(model: ObjectModel) -> Truth:
    return _truth(*primitives.analytic_torus(model.vertices, *TORUS_MM))


def _cylinder_truth(model: ObjectModel, n_along: int) -> Truth:
    radius, height = CYLINDER_MM
    v = model.vertices
    spacing = height / (n_along - 1)
    radial = np.hypot(v[:, 0], v[:, 1])
    # Side vertices only (the two cap centres have radial 0), away from the sharp cap rims.
    measured = (radial > 0.5 * radius) & (np.abs(v[:, 2]) < height / 2 - 2 * spacing)
    safe = np.where(measured[:, None], v, [[radius, 0.0, 0.0]])
    return _truth(*primitives.analytic_cylinder(safe, radius), measured)


def surfaces(
    quick: bool,
) -> dict[str, list[tuple[Callable[[], ObjectModel], Callable[[ObjectModel], Truth]]]]:
    """Per surface, (build mesh, analytic truth) per resolution, coarse to fine (three levels if quick)."""
    levels = slice(0, 3) if quick else slice(None)
    table = {
        "sphere": [(lambda s=s: primitives.sphere(SPHERE_R_MM, s), _sphere_truth) for s in (3, 4, 5, 6)],
        "ellipsoid": [
            (lambda s=s: primitives.ellipsoid(ELLIPSOID_AXES_MM, s), _ellipsoid_truth) for s in (3, 4, 5, 6)
        ],
        "torus": [(lambda g=g: primitives.torus(*TORUS_MM, *g), _torus_truth) for g in GRIDS],
        "cylinder": [
            (lambda g=g: primitives.cylinder(*CYLINDER_MM, *g), lambda m, g=g: _cylinder_truth(m, g[1]))
            for g in GRIDS
        ],
    }
    return {name: rows[levels] for name, rows in table.items()}


def _fresh_curvature(vertices: np.ndarray, triangles: np.ndarray, name: str, method: str):
    """Curvature on a new ObjectModel, so nothing cached (normals, watertightness) hides its cost."""
    return ObjectModel(vertices, triangles, name=name).compute_curvature(method)


def _stats(errors: np.ndarray) -> tuple[float, float]:
    return float(errors.mean()), float(errors.max())


def measure(quick: bool = False, repeats: int = 3) -> dict:
    """Run every method on every surface and resolution; returns rows for the normal and curvature tables."""
    normal_rows, curvature_rows = [], []
    jobs = [(name, build, truth_of) for name, rows in surfaces(quick).items() for build, truth_of in rows]
    for name, build, truth_of in tqdm(jobs, desc="geometry", unit="mesh", disable=None, file=sys.stderr):
        model = build()
        truth = truth_of(model)
        keep = truth.measured
        vertices, triangles = model.vertices, model.triangles
        base = {"surface": name, "vertices": model.n_vertices, "measured_vertices": int(keep.sum())}
        for method in NORMAL_METHODS:
            with quiet_stdout():
                seconds, normals = median_time(partial(vertex_normals, vertices, triangles, method), repeats)
            cosine = np.clip(np.einsum("ij,ij->i", normals[keep], truth.normals[keep]), -1.0, 1.0)
            mean_deg, max_deg = _stats(np.degrees(np.arccos(cosine)))
            normal_rows.append(
                base | {"method": method, "seconds": seconds, "mean_deg": mean_deg, "max_deg": max_deg}
            )
        for method in CURVATURE_METHODS:
            with quiet_stdout():
                run = partial(_fresh_curvature, vertices, triangles, model.name, method)
                seconds, curvature = median_time(run, repeats)
            h_err = 100 * np.abs(curvature.mean - truth.mean)[keep] / np.abs(truth.mean[keep]).max()
            k_err = 100 * np.abs(curvature.gaussian - truth.gaussian)[keep] / truth.gaussian_scale
            h_mean, h_max = _stats(h_err)
            k_mean, k_max = _stats(k_err)
            curvature_rows.append(
                base
                | {
                    "method": method,
                    "seconds": seconds,
                    "H_mean_pct": h_mean,
                    "H_max_pct": h_max,
                    "K_mean_pct": k_mean,
                    "K_max_pct": k_max,
                }
            )
    return {
        "normals": normal_rows,
        "curvature": curvature_rows,
        "convergence": convergence(normal_rows, "mean_deg", NORMAL_FLOOR_DEG)
        + convergence(curvature_rows, "H_mean_pct", CURVATURE_FLOOR_PCT)
        + convergence(curvature_rows, "K_mean_pct", CURVATURE_FLOOR_PCT),
    }


def convergence(rows: list[dict], error_key: str, floor: float) -> list[dict]:
    """Observed order p (err ~ h^p, h ~ V^-1/2) and coarsest/finest error ratio per surface and method.

    Errors under ``floor`` are round-off (the answer is exact, e.g. Max's weights on a sphere) and are left out
    of the fit; with fewer than two levels above it, order and ratio are None.
    """
    out = []
    for surface, method in dict.fromkeys((r["surface"], r["method"]) for r in rows):
        series = [r for r in rows if r["surface"] == surface and r["method"] == method]
        spacing = np.array([r["vertices"] for r in series], float) ** -0.5
        error = np.array([r[error_key] for r in series])
        usable = error > floor
        order = (
            float(np.polyfit(np.log(spacing[usable]), np.log(error[usable]), 1)[0])
            if usable.sum() >= 2
            else None
        )
        ratio = float(error[0] / error[-1]) if usable[0] and usable[-1] else None
        out.append(
            {
                "surface": surface,
                "method": method,
                "error": error_key,
                "order": order,
                "coarse_over_fine": ratio,
            }
        )
    return out


def _print_tables(result: dict) -> None:
    m = result["machine"]
    print(
        f"machine: {m['platform']} ({m['processor']}), {m['cores_available']} of {m['cpu_count']} cores; "
        f"times are medians of {result['repeats']} runs"
    )
    print("\nvertex normals: angle to the analytic normal (degrees)")
    print(f"{'surface':<10} {'vertices':>8} {'method':<11} {'seconds':>9} {'mean deg':>10} {'max deg':>10}")
    for r in result["normals"]:
        print(
            f"{r['surface']:<10} {r['vertices']:>8} {r['method']:<11} {r['seconds']:>9.4f} "
            f"{r['mean_deg']:>10.2e} {r['max_deg']:>10.2e}"
        )
    print("\ncurvature: |H - H_true| / max|H_true| and |K - K_true| / max|K_true| (%)")
    print(
        f"{'surface':<10} {'vertices':>8} {'method':<13} {'seconds':>9} "
        f"{'H mean %':>10} {'H max %':>10} {'K mean %':>10} {'K max %':>10}"
    )
    for r in result["curvature"]:
        print(
            f"{r['surface']:<10} {r['vertices']:>8} {r['method']:<13} {r['seconds']:>9.4f} "
            f"{r['H_mean_pct']:>10.2e} {r['H_max_pct']:>10.2e} {r['K_mean_pct']:>10.2e} {r['K_max_pct']:>10.2e}"
        )
    print("\nconvergence of the mean error: order p (err ~ h^p) and coarsest/finest ratio")
    print(f"{'surface':<10} {'method':<13} {'error':<11} {'order p':>8} {'coarse/fine':>12}")
    for r in result["convergence"]:
        order = "at floor" if r["order"] is None else f"{r['order']:.2f}"
        ratio = "-" if r["coarse_over_fine"] is None else f"{r['coarse_over_fine']:.1f}"
        print(f"{r['surface']:<10} {r['method']:<13} {r['error']:<11} {order:>8} {ratio:>12}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="geometry", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result instead of the tables")
    parser.add_argument("--quick", action="store_true", help="three coarsest resolutions only")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (median), default 3")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    result = {"benchmark": "geometry", "quick": args.quick, "repeats": args.repeats, "machine": machine()}
    result |= measure(quick=args.quick, repeats=args.repeats)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        _print_tables(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
