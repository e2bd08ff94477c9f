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

``--before REV`` times the multiview saliency of git revision REV beside today's, mesh after mesh in the same
run (REV's ``perception`` package, from ``git archive``, in a worker process), and states how today's output
agrees with REV's: byte-identical scores, and the share of the 10 interest points within 5 mm of REV's (per
mesh; mean and min over meshes). 969b1cb is the revision before the multiview speed-up (issue 26).

    .venv/bin/python -m benchmarks.saliency [--limit N] [--json] [--methods multiview,mesh,iss] [--peers]
        [--before REV]
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import subprocess
import sys
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


# The worker that runs another revision's multiview saliency: one mesh path per stdin line, one JSON line back
# (the faster of 2 times, the scores and the interest points, as the rows of today's code are measured).
_BEFORE_WORKER = """
import json, sys, time
import numpy as np
from perception.curvature import quiet_stdout
from perception.geometry import ObjectModel, load_object
from perception.saliency import saliency
for line in sys.stdin:
    path = line.strip()
    with quiet_stdout():
        model = load_object(path)
    runs = []
    for _ in range(2):
        copy = ObjectModel(model.vertices.copy(), model.triangles.copy(), name=model.name)
        start = time.perf_counter()
        result = saliency(copy, "multiview")
        runs.append((time.perf_counter() - start, result))
    first = runs[0][1]
    print(json.dumps({"seconds": min(t for t, _ in runs), "scores": first.scores.tobytes().hex(),
                      "points": first.interest_points(%d).tolist()}), flush=True)
"""


class _Before:
    """Revision ``rev``'s ``perception`` package in a temporary folder and a worker process running it."""

    def __init__(self, rev: str):
        root = Path(__file__).resolve().parents[1]
        self._tmp = tempfile.TemporaryDirectory()
        archive = subprocess.run(
            ["git", "-C", str(root), "archive", rev, "perception"], capture_output=True, check=True
        ).stdout
        import tarfile

        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(self._tmp.name, filter="data")
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _BEFORE_WORKER % N_INTEREST],
            cwd=self._tmp.name,
            env={**__import__("os").environ, "PYTHONPATH": self._tmp.name},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def run(self, path: Path) -> dict:
        self._proc.stdin.write(f"{path}\n")
        self._proc.stdin.flush()
        line = self._proc.stdout.readline()
        if not line:
            raise RuntimeError("the --before worker stopped (see its error above)")
        out = json.loads(line)
        return {"seconds": out["seconds"], "scores": bytes.fromhex(out["scores"]), "points": np.array(out["points"])}

    def close(self) -> None:
        self._proc.stdin.close()
        self._proc.wait(timeout=60)
        self._tmp.cleanup()


def _versus_before(model: ObjectModel, before: dict, method_row: dict) -> dict:
    """Today's multiview output against the other revision's: same bytes, share of interest points near."""
    copy = _fresh(model)
    with quiet_stdout():
        result = saliency(copy, "multiview")
    points = result.interest_points(N_INTEREST)
    near = np.linalg.norm(points[:, None] - before["points"][None], axis=2).min(axis=1) <= NEAR_MM
    return {
        "mesh": method_row["mesh"],
        "before_s": before["seconds"],
        "after_s": method_row["seconds"],
        "identical_scores": result.scores.tobytes() == before["scores"],
        "points_within_5mm": float(near.mean()),
    }


def measure(
    folder: Path, limit: int | None, methods: list[str], peers: bool, before_rev: str | None = None
) -> dict:
    items = list_collection(folder)[:limit]
    rows, peer_rows, versus = [], [], []
    before = _Before(before_rev) if before_rev else None
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
            if before is not None and method == "multiview":
                versus.append(_versus_before(model, before.run(path), rows[-1]))
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
    if before is not None:
        before.close()
    compare = None
    if versus:
        compare = {
            "before": before_rev,
            "meshes": len(versus),
            "before_median_s": statistics.median(v["before_s"] for v in versus),
            "after_median_s": statistics.median(v["after_s"] for v in versus),
            "ratio_of_medians": statistics.median(v["after_s"] for v in versus)
            / statistics.median(v["before_s"] for v in versus),
            "median_ratio": statistics.median(v["after_s"] / v["before_s"] for v in versus),
            "identical_scores": sum(v["identical_scores"] for v in versus),
            "points_within_5mm_mean": statistics.fmean(v["points_within_5mm"] for v in versus),
            "points_within_5mm_min": min(v["points_within_5mm"] for v in versus),
        }
    return {
        "meshes": len(items),
        "rows": rows,
        "peers": peer_rows,
        "peer_note": peer_note,
        "summary": summary,
        "versus_before": versus,
        "before": compare,
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
    c = result.get("before")
    if c:
        print(
            f"multiview against {c['before']} ({c['meshes']} meshes, the same run, mesh after mesh): median s / mesh "
            f"{c['before_median_s']:.3f} before, {c['after_median_s']:.3f} now (ratio of medians "
            f"{c['ratio_of_medians']:.2f}, median per-mesh ratio {c['median_ratio']:.2f}); scores byte-identical on "
            f"{c['identical_scores']} of {c['meshes']}; share of the {N_INTEREST} interest points within "
            f"{NEAR_MM:g} mm of {c['before']}'s: mean {c['points_within_5mm_mean']:.3f}, min "
            f"{c['points_within_5mm_min']:.2f}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="saliency", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result after the table")
    parser.add_argument("--limit", type=int, default=None, help="first N meshes only")
    parser.add_argument(
        "--data", type=Path, default=DATA / "shrec07", help="class-per-folder mesh set (default: shrec07)"
    )
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    parser.add_argument("--peers", action="store_true", help="also run the PCL peer (benchmarks/peers)")
    parser.add_argument(
        "--before", metavar="REV", default=None,
        help="also time git revision REV's multiview saliency and measure agreement with it (e.g. 969b1cb)",
    )
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
    if args.before and "multiview" not in methods:
        parser.error("--before compares the multiview method: include it in --methods")
    result |= measure(args.data, args.limit, methods, args.peers, args.before)
    _print_table(result)
    if args.json:
        print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
