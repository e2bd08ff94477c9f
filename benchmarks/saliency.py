"""Saliency run time against agreement with curvature, per method, over the SHREC 2007 watertight meshes.

For every mesh (loaded and scaled to a 150 mm diagonal) and every method of ``perception.saliency``:
time ``saliency(model, method)`` twice on fresh ``ObjectModel`` copies (so cached curvature or ray-casting
scenes do not hide their cost; the per-mesh time is the faster run), check both runs are byte-identical
(determinism) and finite (NaN / Inf), and measure agreement with curvature, since no human saliency ground
truth ships with the data:

- ``spearman``: Spearman rank correlation of the per-vertex scores with |mean curvature| (pymeshlab quadric
  fitting);
- ``near_curved``: the fraction of 10 interest points within 5 mm of a high-curvature vertex (top 10 % of
  |mean curvature|); the fraction of the surface area within 5 mm of one is given as ``chance``.

Mesh saliency is built on mean curvature, so its agreement is partly by construction; ISS and multiview
are not. With ``--peers``, the PCL keypoint detectors (``benchmarks/peers``, built with ``make peers``) run
on the same vertices (detection time inside the program, keypoint counts); they are skipped, saying why, when
the binary is absent. ``--methods ...,pcl_harris,pcl_iss`` scores PCL's keypoints as saliency methods
(``perception.saliency.PCL_METHODS``, with the mesh normals; time includes starting the program).

    .venv/bin/python -m benchmarks.saliency [--limit N] [--json] [--methods multiview,mesh,iss] [--peers]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr
from tqdm import tqdm

from benchmarks._common import DATA, machine
from perception.curvature import quiet_stdout
from perception.geometry import ObjectModel, list_collection, load_object
from perception.saliency import METHODS, PCL_METHODS, saliency

PEER_BINARY = Path(__file__).resolve().parent / "peers" / "pcl_keypoints"
N_INTEREST = 10
NEAR_MM = 5.0
CURVED_FRACTION = 0.10


def _fresh(model: ObjectModel) -> ObjectModel:
    return ObjectModel(model.vertices.copy(), model.triangles.copy(), name=model.name, label=model.label)


def _agreement(model: ObjectModel, scores: np.ndarray, points: np.ndarray) -> dict:
    abs_h = np.abs(model.curvature.mean)
    curved = abs_h >= np.quantile(abs_h, 1 - CURVED_FRACTION)
    tree = cKDTree(model.vertices[curved])
    near = tree.query(points)[0] <= NEAR_MM
    # Chance level: the area fraction of the surface within NEAR_MM of a curved vertex (triangle centroids).
    centroids = model.vertices[model.triangles].mean(axis=1)
    area_near = tree.query(centroids)[0] <= NEAR_MM
    rho = spearmanr(scores, abs_h).statistic if np.ptp(scores) > 0 else 0.0
    return {
        "spearman": float(np.nan_to_num(rho)),
        "near_curved": float(near.mean()),
        "chance": float(model.triangle_areas[area_near].sum() / model.triangle_areas.sum()),
    }


def _run_method(model: ObjectModel, method: str) -> dict:
    runs = []
    for _ in range(2):
        copy = _fresh(model)
        start = time.perf_counter()
        with quiet_stdout():
            result = saliency(copy, method)
        runs.append((time.perf_counter() - start, result))
    (t1, first), (t2, second) = runs
    points = first.interest_points(N_INTEREST)
    return {
        "seconds": min(t1, t2),
        "finite": bool(np.isfinite(first.scores).all() and np.isfinite(points).all()),
        "deterministic": first.scores.tobytes() == second.scores.tobytes(),
        **_agreement(model, first.scores, points),
    }


def _run_peer(model: ObjectModel, reference: np.ndarray) -> dict:
    """PCL ISS and Harris 3D on the vertices: seconds (inside the program), keypoints, and the fraction of
    Open3D ISS keypoints within 2 mm of a PCL ISS keypoint."""
    with tempfile.TemporaryDirectory() as tmp:
        cloud = Path(tmp) / "cloud.xyz"
        np.savetxt(cloud, model.vertices, fmt="%.6f")
        out = {}
        for detector in ("iss", "harris"):
            keys = Path(tmp) / f"{detector}.txt"
            done = subprocess.run(
                [str(PEER_BINARY), detector, str(cloud), str(keys)],
                capture_output=True,
                text=True,
                check=True,
            )
            index = np.loadtxt(keys, dtype=np.int64, ndmin=1)
            out[detector] = {"seconds": float(done.stdout.split()[-1]), "keypoints": len(index)}
            if detector == "iss" and len(index) and len(reference):
                d, _ = cKDTree(model.vertices[index]).query(model.vertices[reference])
                out[detector]["open3d_iss_within_2mm"] = float((d <= 2.0).mean())
    return out


def measure(folder: Path, limit: int | None, methods: list[str], peers: bool) -> dict:
    items = list_collection(folder)[:limit]
    rows, peer_rows = [], []
    peer_note = None
    if peers and not PEER_BINARY.exists():
        peer_note = (
            f"PCL peer skipped: {PEER_BINARY} is absent (build it with `make peers`)"
        )
    for path, label in tqdm(items, desc="saliency", disable=None):
        with quiet_stdout():
            model = load_object(path, label=label)
        for method in methods:
            rows.append({"mesh": f"{label}/{path.stem}", "method": method, **_run_method(model, method)})
        if peers and peer_note is None:
            from perception.mesh_saliency import iss_keypoints

            peer_rows.append({"mesh": f"{label}/{path.stem}", **_run_peer(model, iss_keypoints(model))})
    summary = []
    for method in methods:
        r = [row for row in rows if row["method"] == method]
        summary.append(
            {
                "method": method,
                "meshes": len(r),
                "median_s": statistics.median(x["seconds"] for x in r),
                "max_s": max(x["seconds"] for x in r),
                "all_finite": all(x["finite"] for x in r),
                "all_deterministic": all(x["deterministic"] for x in r),
                "spearman_median": statistics.median(x["spearman"] for x in r),
                "near_curved_mean": statistics.fmean(x["near_curved"] for x in r),
                "chance_mean": statistics.fmean(x["chance"] for x in r),
            }
        )
    if peer_rows:
        for detector in ("iss", "harris"):
            times = [p[detector]["seconds"] for p in peer_rows]
            summary.append(
                {
                    "method": f"pcl_{detector}",
                    "meshes": len(peer_rows),
                    "median_s": statistics.median(times),
                    "max_s": max(times),
                    "keypoints_median": statistics.median(p[detector]["keypoints"] for p in peer_rows),
                }
            )
    return {
        "meshes": len(items),
        "rows": rows,
        "peers": peer_rows,
        "peer_note": peer_note,
        "summary": summary,
    }


def _print_table(result: dict) -> None:
    m = result["machine"]
    print(f"machine: {m['platform']} ({m['processor']}), {m['cores_available']} of {m['cpu_count']} cores")
    print(
        f"{result['meshes']} SHREC 2007 meshes; time = faster of 2 runs per mesh, then median / max over meshes"
    )
    print(
        f"{'method':<10} {'median s':>9} {'max s':>8} {'finite':>7} {'determ.':>8} "
        f"{'spearman':>9} {'near curved':>12} {'chance':>7}"
    )
    for s in result["summary"]:
        if "spearman_median" not in s:
            print(
                f"{s['method']:<10} {s['median_s']:>9.3f} {s['max_s']:>8.3f}  (--peers: detection inside the program "
                f"only; keypoints median {s['keypoints_median']})"
            )
            continue
        print(
            f"{s['method']:<10} {s['median_s']:>9.3f} {s['max_s']:>8.3f} {s['all_finite']!s:>7} "
            f"{s['all_deterministic']!s:>8} {s['spearman_median']:>9.3f} {s['near_curved_mean']:>12.2f} "
            f"{s['chance_mean']:>7.2f}"
        )
    if result["peer_note"]:
        print(result["peer_note"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="saliency", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    parser.add_argument("--limit", type=int, default=None, help="first N meshes only")
    parser.add_argument(
        "--data", type=Path, default=DATA / "shrec07", help="class-per-folder mesh set (default: shrec07)"
    )
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    parser.add_argument("--peers", action="store_true", help="also run the PCL peer (benchmarks/peers)")
    args = parser.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    unknown = sorted(set(methods) - set(METHODS + PCL_METHODS))
    if unknown:
        parser.error(f"unknown methods {unknown}; choose from {', '.join(METHODS + PCL_METHODS)}")
    if args.limit is not None and args.limit < 1:
        parser.error("--limit must be at least 1")
    if not args.data.is_dir():
        print(f"no data at {args.data}: pass --data FOLDER")
        return 1
    result = {"benchmark": "saliency", "machine": machine(), "methods": methods}
    result |= measure(args.data, args.limit, methods, args.peers)
    _print_table(result)
    if args.json:
        print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
