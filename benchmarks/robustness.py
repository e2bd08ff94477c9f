"""What the crash-safety of issue 13 costs per mesh, on the 100 SHREC 2007 meshes of the shared data.

Per mesh, the time the safe path adds over the old in-process pymeshlab path, step by step:

- repair: the numpy clean-up (``perception.meshio.repair``) minus pymeshlab's four clean-up filters;
- orient: :func:`perception.orientation.orient_outward` (new; the old path had none);
- normals: numpy angle-weighted vertex normals minus pymeshlab ``compute_normal_per_vertex``;
- isolate: the forked child around the default ("quadric") curvature fit: the parent's wall time of
  :func:`perception.isolate.run_isolated` minus the fit's own time measured inside the child (so the old
  in-process fit is timed without running it in this process, where it may abort).

``added`` is their sum. Times are per-mesh medians of ``--repeats`` runs; the table gives the median and
the max over meshes (milliseconds), next to the old path's total for scale.

    .venv/bin/python -m benchmarks.robustness [--repeats N] [--limit N] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
from tqdm import tqdm

from benchmarks._common import DATA, machine, median_time
from perception import curvature, meshio
from perception.geometry import list_collection, normalize
from perception.isolate import run_isolated
from perception.orientation import orient_outward

STEPS = ("repair", "orient", "normals", "isolate")


def _pymeshlab_repair(vertices: np.ndarray, triangles: np.ndarray):
    """The old clean-up: pymeshlab's filters, in this process (safe on these meshes: it always ran here)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=triangles))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_unreferenced_vertices()
    mesh = ms.current_mesh()
    return mesh.vertex_matrix(), mesh.face_matrix()


def _pymeshlab_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    ms = curvature._meshset(vertices, triangles)
    ms.compute_normal_per_vertex(weightmode="By Angle")
    return ms.current_mesh().vertex_normal_matrix()


def _timed_fit(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """In the child: the quadric fit's own time, s."""
    start = time.perf_counter()
    curvature._estimate(vertices, triangles, "quadric", "bench")
    return time.perf_counter() - start


def _isolation_overhead(vertices: np.ndarray, triangles: np.ndarray) -> tuple[float, float]:
    """(parent wall time minus in-child fit time, fit time), s."""
    start = time.perf_counter()
    inside = run_isolated(_timed_fit, vertices, triangles, timeout_s=300.0, what="benchmark fit")
    return time.perf_counter() - start - inside, inside


def measure_mesh(path, repeats: int) -> dict:
    """Per-step added seconds (medians of ``repeats``) and the old path's total for one mesh file."""
    raw = meshio.read_mesh(path)
    vertices, triangles = meshio.validate_arrays(raw.vertices, raw.triangles, str(path))
    t_old_repair, _ = median_time(lambda: _pymeshlab_repair(vertices, triangles), repeats)
    t_new_repair, (v, t, _) = median_time(lambda: meshio.repair(vertices, triangles, None, str(path)), repeats)
    v, _ = normalize(v)
    t_orient, (t, _) = median_time(lambda: orient_outward(v, t, str(path)), repeats)
    t_old_normals, _ = median_time(lambda: _pymeshlab_normals(v, t), repeats)
    t_new_normals, _ = median_time(lambda: curvature.vertex_normals(v, t, "angle"), repeats)
    runs = [_isolation_overhead(v, t) for _ in range(repeats)]
    overhead = statistics.median(r[0] for r in runs)
    fit = statistics.median(r[1] for r in runs)
    added = {
        "repair": t_new_repair - t_old_repair,
        "orient": t_orient,
        "normals": t_new_normals - t_old_normals,
        "isolate": overhead,
    }
    return {
        "mesh": f"{path.parent.name}/{path.name}",
        "vertices": len(v),
        "added_s": added | {"total": sum(added.values())},
        "old_path_s": t_old_repair + t_old_normals + fit,
    }


def measure(repeats: int, limit: int | None) -> dict:
    items = list_collection(DATA / "shrec07")[:limit]
    rows = [measure_mesh(path, repeats) for path, _ in tqdm(items, desc="meshes", leave=False)]
    summary = {}
    for key in (*STEPS, "total"):
        values = [r["added_s"][key] for r in rows]
        summary[key] = {"median_ms": 1e3 * statistics.median(values), "max_ms": 1e3 * max(values)}
    old = [r["old_path_s"] for r in rows]
    summary["old_path"] = {"median_ms": 1e3 * statistics.median(old), "max_ms": 1e3 * max(old)}
    return {"meshes": len(rows), "summary": summary, "per_mesh": rows}


def _print_table(result: dict) -> None:
    m = result["machine"]
    print(
        f"machine: {m['platform']} ({m['processor']}), {m['cores_available']} of {m['cpu_count']} cores; "
        f"{result['meshes']} SHREC 2007 meshes, per-mesh medians of {result['repeats']} runs"
    )
    print("\nadded time per mesh of the crash-safe path over the old in-process path (ms)")
    print(f"{'step':<10} {'median ms':>10} {'max ms':>10}")
    for key in (*STEPS, "total"):
        row = result["summary"][key]
        print(f"{key:<10} {row['median_ms']:>10.1f} {row['max_ms']:>10.1f}")
    old = result["summary"]["old_path"]
    print(f"{'old path':<10} {old['median_ms']:>10.1f} {old['max_ms']:>10.1f}   (repair + normals + quadric fit)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robustness", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result instead of the table")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats per mesh (median), default 3")
    parser.add_argument("--limit", type=int, default=None, help="only the first N meshes (a quick look)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if not (DATA / "shrec07").is_dir():
        parser.error(f"{DATA / 'shrec07'} is absent (set VISUOTACTILE_DATA to the shared data folder)")
    result = {"benchmark": "robustness", "repeats": args.repeats, "machine": machine()}
    result |= measure(args.repeats, args.limit)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        _print_table(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
