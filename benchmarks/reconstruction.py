"""Reconstruction benchmark: surface error against run time for RGB-D captures and point-cloud files.

(a) Virtual OAK-D (400p, stereo noise, seeded) around built-in objects on a table, reconstructed with
    :func:`perception.reconstruct.multiview.reconstruct_frames`: surface error (distance from 20k points drawn on the
    reconstruction to the true mesh, mm: mean and 95th percentile) against the number of views (at 500 mm,
    Poisson depth 7), the camera distance (4 views) and the Poisson depth (4 views at 500 mm), plus the
    same capture without ICP refinement, and the open surface of the seen points alone (``close=False``,
    trimmed by density, as before the closure). Completeness ("cover p95"): the 95th percentile distance
    from the true surface to the reconstruction (the unseen bottom counts). "Seen": the error of the
    surface within 2 mm of a captured point (left out: what the closure adds where no camera looked).
    Closure: the fraction of
    watertight reconstructions, their volume over the true volume, and the distance between the
    bounding-box centres (the point contour planes pass through), mm. Times: capture (ray casting +
    stereo model) and reconstruction, median over the objects.
(b) Point-cloud files: 15k points sampled on each object, written as PCD / XYZ / PLY (no faces) / NPZ,
    loaded back with :func:`perception.reconstruct.surface.load_points` (estimated normals, Poisson depth 7):
    error and completeness as in (a).
(c) The real GraspNet RealSense frame (shared data): table plane, object clusters (``smooth`` and the default
    ``convex`` segmentation), cluster centres matched one-to-one (Hungarian) to the 9 annotated object poses,
    the clusters holding two annotated objects (merged; see :func:`real_frame`), and the cracker box, soup can,
    banana and drill picked by the pixel of their annotated pose, with their size; ``--figure`` writes a
    figure of it.

    .venv/bin/python -m benchmarks.reconstruction [--quick] [--json] [--objects K] [--figure PATH]
        [--sweep all|default] [--parts abc] [--per-object]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._common import DATA, machine
from perception.camera import VirtualOakCamera, read_recording
from perception.reconstruct.multiview import reconstruct_frames
from perception.reconstruct.pointfiles import write_points
from perception.reconstruct.surface import load_points, sample_surface, surface_error
from perception.reconstruct.tabletop import frames_to_points, segment_table
from perception.shapes import CLASSES, make_object

VIEWS = (1, 2, 4, 8)
DISTANCES_MM = (400.0, 500.0, 700.0, 1000.0)
DEPTHS = (6, 7, 8)
FORMATS = (".pcd", ".xyz", ".ply", ".npz")


def _settings(quick: bool, sweep: str = "all") -> list[dict]:
    if sweep == "default":
        return [{"sweep": "default", "views": 4, "distance_mm": 500.0, "depth": 7, "icp": True}]
    views = (1, 4) if quick else VIEWS
    distances = (500.0,) if quick else DISTANCES_MM
    depths = (6, 7) if quick else DEPTHS
    rows = [{"sweep": "views", "views": v, "distance_mm": 500.0, "depth": 7, "icp": True} for v in views]
    rows += [{"sweep": "distance", "views": 4, "distance_mm": d, "depth": 7, "icp": True} for d in distances]
    rows += [{"sweep": "depth", "views": 4, "distance_mm": 500.0, "depth": d, "icp": True} for d in depths]
    rows.append({"sweep": "no icp", "views": 4, "distance_mm": 500.0, "depth": 7, "icp": False})
    rows.append({"sweep": "open", "views": 4, "distance_mm": 500.0, "depth": 7, "icp": True, "close": False})
    return rows


def _volume(model) -> float:
    """Enclosed volume (divergence theorem), mm^3; meaningful for closed surfaces only."""
    a, b, c = (model.vertices[model.triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def views_sweep(classes: list[str], quick: bool, seed: int, sweep: str = "all") -> list[dict]:
    rows = []
    for setting in _settings(quick, sweep):
        per_object = []
        for name in classes:
            camera = VirtualOakCamera(make_object(name, 0), seed=seed)
            start = time.perf_counter()
            frames = camera.capture_views(setting["views"], setting["distance_mm"])
            t_capture = time.perf_counter() - start
            start = time.perf_counter()
            close = setting.get("close", True)
            rec = reconstruct_frames(frames, target=camera.target, poisson_depth=setting["depth"], icp=setting["icp"],
                                     seed=seed, close=close, density_trim=None if close else 1.0)
            t_rec = time.perf_counter() - start
            err = surface_error(rec.model, camera.truth, seed=seed, seen=rec.points)
            closed = rec.model.is_watertight
            per_object.append({"object": name, **err, "capture_s": t_capture, "reconstruct_s": t_rec,
                               "points": len(rec.points), "triangles": rec.model.n_triangles, "watertight": closed,
                               "volume_ratio": _volume(rec.model) / _volume(camera.truth) if closed else float("nan"),
                               "centre_mm": float(np.linalg.norm(rec.model.bounds.mean(axis=0) - camera.truth.bounds.mean(axis=0)))})
        rows.append({
            **setting,
            "mean_mm": statistics.fmean(r["mean_mm"] for r in per_object),
            "p95_mm": statistics.fmean(r["p95_mm"] for r in per_object),
            "worst_p95_mm": max(r["p95_mm"] for r in per_object),
            "coverage_p95_mm": statistics.fmean(r["coverage_p95_mm"] for r in per_object),
            "seen_mean_mm": statistics.fmean(r["seen_mean_mm"] for r in per_object),
            "seen_p95_mm": statistics.fmean(r["seen_p95_mm"] for r in per_object),
            "watertight": statistics.fmean(r["watertight"] for r in per_object),
            "centre_mm": statistics.fmean(r["centre_mm"] for r in per_object),
            "capture_s": statistics.median(r["capture_s"] for r in per_object),
            "reconstruct_s": statistics.median(r["reconstruct_s"] for r in per_object),
            "points": int(statistics.median(r["points"] for r in per_object)),
            "objects": per_object,
        })
    return rows


def files_sweep(classes: list[str], seed: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in classes:
            truth = make_object(name, 0)
            points = sample_surface(truth, 15000, np.random.default_rng(seed))
            for suffix in FORMATS:
                path = write_points(Path(tmp) / f"{name}{suffix}", points)
                start = time.perf_counter()
                model = load_points(path, size_mm=None, poisson_depth=7)
                seconds = time.perf_counter() - start
                rows.append({"object": name, "format": suffix[1:], **surface_error(model, truth), "load_s": seconds})
    return rows


#: GraspNet ids of the four YCB objects picked by pixel in (c), with their names.
PICKS = {0: "cracker box", 2: "tomato soup can", 5: "banana", 8: "power drill"}
#: Their longest side, mm (bounding boxes of the shared YCB meshes 003, 005, 011, 035).
LONGEST_MM = {0: 213.0, 2: 102.0, 5: 178.0, 8: 187.0}
#: A cluster longer than its object's longest side by more than this holds more than the object, mm.
SIZE_SLACK_MM = 30.0


def real_frame(figure: str | None, method: str = "convex") -> dict | None:
    """(c): segment the GraspNet frame, match clusters to the 9 annotated poses, decide merges, pick 4 by pixel.

    Merged, two tests. For all 9 objects: each annotated object's pixel (its pose's translation projected through the intrinsics) shows
    its surface; the cluster holding most of the measured points in the 13 x 13 pixels around it (within
    4 mm of a cluster point) holds that object; a cluster holding two annotated objects is merged. For the four
    YCB objects (known size): the cluster matched to one is longer than the object by more than
    ``SIZE_SLACK_MM`` (it holds something else too: a neighbour or a fixture).
    """
    from scipy.io import loadmat
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree
    from scipy.spatial.distance import cdist

    from perception.reconstruct.tabletop import describe_objects, pick_pixel

    folder = DATA / "rgbd" / "graspnet_tabletop"
    if not folder.is_dir():
        return None
    (frame,) = read_recording(folder)
    start = time.perf_counter()
    points, colors, views = frames_to_points([frame], drop_flying=True)  # as the camera path does
    scene = segment_table(points, colors, views, method=method)
    seconds = time.perf_counter() - start
    meta = loadmat(folder / "meta.mat")
    origins = meta["poses"][:, 3, :].T * 1000.0
    ids = (meta["cls_indexes"][0] - 1).tolist()
    k = frame.intrinsics
    pixels = np.stack([k.fx * origins[:, 0] / origins[:, 2] + k.cx, k.fy * origins[:, 1] / origins[:, 2] + k.cy], 1)
    tree = cKDTree(scene.points)
    holder = []
    for u, v in np.rint(pixels).astype(int):
        rows, cols = np.mgrid[v - 6:v + 7, u - 6:u + 7].reshape(2, -1)
        z = frame.depth_mm[rows, cols].astype(np.float64)
        ok = z > 0
        near = np.stack([(cols[ok] - k.cx) * z[ok] / k.fx, (rows[ok] - k.cy) * z[ok] / k.fy, z[ok]], 1)
        dist, nearest = tree.query(near)
        labels = scene.labels[nearest[dist <= 4.0]]
        labels = labels[labels >= 0]
        holder.append(int(np.bincount(labels).argmax()) if len(labels) else -1)
    distance = cdist(origins, np.array([c.center for c in scene.clusters]))
    rows, cols = linear_sum_assignment(distance)
    held, counts = np.unique([h for h in holder if h >= 0], return_counts=True)
    merged = [int(h) for h, n in zip(held, counts) if n > 1]
    matches = [{"graspnet_id": int(ids[r]), "cluster": int(c), "distance_mm": float(distance[r, c]),
                "holder": holder[r], "size_mm": [round(float(x), 1) for x in scene.clusters[c].size_mm],
                "too_long": (bool(scene.clusters[c].size_mm[0] > LONGEST_MM[ids[r]] + SIZE_SLACK_MM)
                             if ids[r] in LONGEST_MM else "")}
               for r, c in zip(rows, cols)]
    picks = []
    for gid, name in PICKS.items():
        u, v = (float(x) for x in np.rint(pixels[ids.index(gid)]))
        index, warnings = pick_pixel(scene, frame, (u, v))
        cluster = scene.clusters[index]
        picks.append({"graspnet_id": gid, "object": name, "pixel": f"{u:.0f},{v:.0f}", "cluster": index,
                      "centre_error_mm": float(np.linalg.norm(cluster.center - origins[ids.index(gid)])),
                      "length_mm": float(cluster.size_mm[0]), "width_mm": float(cluster.size_mm[1]),
                      "height_mm": float(cluster.size_mm[2]), "warnings": warnings + cluster.warnings})
    result = {
        "method": method,
        "plane": scene.plane.tolist(),
        "table_points": scene.n_table_points,
        "clusters": len(scene.clusters),
        "matched_within_30mm": int(sum(m["distance_mm"] <= 30.0 for m in matches)),
        "merged_clusters": merged,
        "too_long": [m["graspnet_id"] for m in matches if m["too_long"] is True],
        "matches": matches,
        "objects": describe_objects(scene, frame),
        "picks": picks,
        "segment_s": seconds,
    }
    if figure:
        result["figure"] = str(_real_figure(frame, scene, origins, ids, Path(figure)))
    return result


def _real_figure(frame, scene, origins, ids, path: Path) -> Path:
    from matplotlib.figure import Figure

    from perception.atomic import save_figure

    k = frame.intrinsics
    project = lambda p: (k.fx * p[:, 0] / p[:, 2] + k.cx, k.fy * p[:, 1] / p[:, 2] + k.cy)
    fig = Figure(figsize=(12, 3.8))
    ax0, ax1 = fig.subplots(1, 2)
    ax0.imshow(frame.color)
    ax0.set_title("GraspNet RealSense frame")
    labels = scene.labels
    for mask, color in ((labels == -2, "0.8"), (labels == -1, "0.93")):
        ax1.scatter(*project(scene.points[mask]), s=0.1, c=color, rasterized=True)
    objects = labels >= 0
    ax1.scatter(*project(scene.points[objects]), s=0.2, c=labels[objects] % 20, cmap="tab20", vmin=0, vmax=19,
                rasterized=True)
    ax1.plot(*project(np.array([c.center for c in scene.clusters])), "k+", ms=9, label="cluster centre")
    ax1.plot(*project(origins), "rx", ms=7, label="annotated pose")
    for (u, v), i in zip(np.stack(project(origins), axis=1), ids):
        ax1.annotate(str(i), (u, v), color="r", fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax1.set_xlim(0, k.width)
    ax1.set_ylim(k.height, 0)
    ax1.set_aspect("equal")
    ax1.legend(loc="lower left", fontsize=7)
    ax1.set_title(f"table plane + {len(scene.clusters)} clusters")
    for ax in (ax0, ax1):
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def _print_table(title: str, rows: list[dict], columns: list[tuple[str, str]]) -> None:
    print(f"\n{title}")
    widths = [max(len(head), 9) for head, _ in columns]
    print("  ".join(head.rjust(w) for (head, _), w in zip(columns, widths)))
    for row in rows:
        cells = []
        for (head, key), w in zip(columns, widths):
            value = row.get(key, "")
            cells.append((f"{value:.4g}" if isinstance(value, float) else str(value)).rjust(w))
        print("  ".join(cells))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.reconstruction", description=__doc__.split("\n")[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result after the tables")
    parser.add_argument("--quick", action="store_true", help="one object, fewer settings")
    parser.add_argument("--objects", type=int, default=None, help="built-in classes to use (default 3, quick 1)")
    parser.add_argument("--figure", default=None, help="write the real-frame segmentation figure here (PNG)")
    parser.add_argument("--sweep", choices=("all", "default"), default="all",
                        help="all: views, distance, depth and ICP sweeps; default: only 4 views at 500 mm, depth 7")
    parser.add_argument("--parts", default="abc", help="which parts to run (default abc)")
    parser.add_argument("--per-object", action="store_true", help="print (a) per object too")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    n = args.objects or (1 if args.quick else 3)
    preferred = ["bottle", "mug", "box", "can", "bowl", "wineglass", "hammer", "funnel", "spoon", "ring"]
    classes = [c for c in preferred if c in CLASSES][:n]

    result = {"machine": machine(), "classes": classes}
    if "a" in args.parts:
        _part_a(result, classes, args)
    if "b" in args.parts:
        _part_b(result, classes, args)
    if "c" in args.parts:
        _part_c(result, args)
    if args.json:
        json.dump(result, sys.stdout, indent=2, default=str)
        sys.stdout.write("\n")
    return 0


def _part_a(result: dict, classes: list[str], args) -> None:
    result["views"] = views_sweep(classes, args.quick, args.seed, args.sweep)
    _print_table(
        f"(a) virtual OAK-D 400p -> reconstruction, surface error to the true mesh (mean over {', '.join(classes)})",
        result["views"],
        [("sweep", "sweep"), ("views", "views"), ("dist mm", "distance_mm"), ("depth", "depth"), ("icp", "icp"),
         ("mean mm", "mean_mm"), ("p95 mm", "p95_mm"), ("worst p95", "worst_p95_mm"), ("cover p95", "coverage_p95_mm"),
         ("seen mean", "seen_mean_mm"), ("seen p95", "seen_p95_mm"), ("closed", "watertight"), ("centre mm", "centre_mm"), ("points", "points"), ("capture s", "capture_s"),
         ("recon s", "reconstruct_s")],
    )
    if args.per_object:
        _print_table(
            "(a) per object",
            [{**o, "views": r["views"], "distance_mm": r["distance_mm"], "depth": r["depth"], "icp": r["icp"]}
             for r in result["views"] for o in r["objects"]],
            [("object", "object"), ("views", "views"), ("dist mm", "distance_mm"), ("depth", "depth"),
             ("icp", "icp"), ("mean mm", "mean_mm"), ("p95 mm", "p95_mm"), ("cover p95", "coverage_p95_mm"),
             ("seen p95", "seen_p95_mm"), ("closed", "watertight"), ("volume", "volume_ratio"), ("centre mm", "centre_mm"), ("recon s", "reconstruct_s")],
        )


def _part_b(result: dict, classes: list[str], args) -> None:
    result["files"] = files_sweep(classes, args.seed)
    _print_table(
        "(b) point-cloud files (15k samples) -> load_points, error to the true mesh",
        result["files"],
        [("object", "object"), ("format", "format"), ("mean mm", "mean_mm"), ("p95 mm", "p95_mm"),
         ("max mm", "max_mm"), ("cover p95", "coverage_p95_mm"), ("load s", "load_s")],
    )


def _part_c(result: dict, args) -> None:
    for method in ("smooth", "convex"):
        real = real_frame(args.figure if method == "convex" else None, method)
        if real is None:
            return
        result["real_frame" if method == "convex" else "real_frame_smooth"] = real
        _print_table(
            f"(c) GraspNet frame, {method} segmentation: {real['clusters']} clusters, {real['matched_within_30mm']} of 9 "
            f"annotated objects within 30 mm, clusters holding two annotated objects: {real['merged_clusters'] or 'none'}, "
            f"YCB objects in a cluster longer than the object: {real['too_long'] or 'none'} ({real['segment_s']:.2f} s)",
            real["matches"],
            [("graspnet id", "graspnet_id"), ("cluster", "cluster"), ("dist mm", "distance_mm"),
             ("holder", "holder"), ("size mm", "size_mm"), ("too long", "too_long")],
        )
    _print_table(
        "(c) picked by the pixel of the annotated pose (visuotactile camera --target U,V), convex segmentation",
        real["picks"],
        [("object", "object"), ("pixel", "pixel"), ("cluster", "cluster"), ("centre err", "centre_error_mm"),
         ("length mm", "length_mm"), ("width mm", "width_mm"), ("height mm", "height_mm"), ("warnings", "warnings")],
    )


if __name__ == "__main__":
    sys.exit(main())
