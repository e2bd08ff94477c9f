"""Tactile benchmark: imprint error against run time, press throughput against raw ray casting, slicing.

(a) Imprint. The FSR pad (gap mode) is pressed on a sphere (R = 10 and 50 mm; the pad is tangent where a
    ray from the centre meets the mesh, analytic gap R - sqrt(R^2 - r^2) at taxel distance r), on the side
    of a cylinder (R = 30 mm; gap R - sqrt(R^2 - y^2) across the axis) and on a plane (gap 0), at taxel
    resolutions 8..64 and several mesh resolutions. Error = max |gap - analytic| over the taxels that see
    the surface (analytic r < R and a reading below the range), in % of the analytic imprint's depth
    range over those taxels; on the plane, where the range is zero, the error is in mm. Rows marked
    ``face`` orient the pad with the flat face normal instead of the interpolated one.
(b) Throughput. Frames/s of ``FSRSensor.press`` with adaptive pads on SHREC 2007 meshes (25-probe
    contours on random planes through the centre), next to raw ``scene.cast_rays`` frames/s on the same
    scene in the same run (1,024 rays per frame: the full-side rays of the same probes, built once), and
    their ratio. Also the rays cast per frame by the adaptive pad and the fraction of pads that shrank.
    Times are medians of ``--repeats`` runs, ours and raw interleaved. The adaptive pad's error is the
    fraction of pads whose side equals the reference rule's (shrink one ladder step at a time, re-cast
    the full pad each step), ``= stepwise``.
(c) Slicing. Time per plane of :func:`tactile.contours.section_chains` next to trimesh's
    ``Trimesh.section`` (the peer), and the largest relative difference of their section lengths.

    .venv/bin/python -m benchmarks.tactile [--quick] [--json] [--repeats N] [--meshes K] [--contours C]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
from functools import partial

import numpy as np
import open3d as o3d
from tqdm import tqdm

from benchmarks._common import DATA, machine, median_time
from perception import primitives
from perception.errors import ContourError
from perception.geometry import ObjectModel, list_collection, load_object
from tactile.contours import interpolate_normals, make_contour, plane_through, section_chains
from tactile.sensor import FSRSensor

TAXELS = (8, 16, 32, 64)
SPHERE_SUBDIVISIONS = (3, 4, 5, 6)
CYLINDER_AROUND = (32, 64, 128, 256)
PLANE_GRIDS = (11, 41)
SPHERE_DIRECTION = np.array([0.2, -0.3, 0.9]) / np.linalg.norm([0.2, -0.3, 0.9])
RAYS_PER_FRAME = 1024


def _surface_pose(model: ObjectModel, direction: np.ndarray, normal: str):
    """Where the ray from the origin along ``direction`` meets the mesh, with its interpolated or face normal."""
    ray = np.r_[0.0, 0.0, 0.0, direction].astype(np.float32)[None]
    hit = model.scene.cast_rays(o3d.core.Tensor(ray))
    point = direction * float(hit["t_hit"].numpy()[0])
    tri = hit["primitive_ids"].numpy().astype(np.int64)
    n = (
        interpolate_normals(model, point[None], tri)
        if normal == "interpolated"
        else model.triangle_normals[tri]
    )
    return point[None], n


# --------------------------------------------------------------------------------------- imprint
def _imprint_row(shape, resolution, model, taxels, normal, position, normals, tangent, analytic_fn, repeats):
    sensor = FSRSensor(rows=taxels, cols=taxels)
    seconds = median_time(lambda: sensor.press(model, position, normals, tangent), repeats)[0]
    gaps = sensor.measure_gaps(model, position, normals, tangent, np.array([sensor.side_mm]))[0]
    analytic, defined = analytic_fn(sensor.taxel_coordinates())
    seen = defined & (gaps < sensor.range_mm)
    diff = np.abs(gaps[seen] - analytic[seen]).max()
    depth = float(np.ptp(analytic[seen]))
    row = {
        "shape": shape,
        "mesh": resolution,
        "triangles": model.n_triangles,
        "taxels": taxels,
        "normal": normal,
        "time_ms": 1e3 * seconds,
        "taxels_seen": int(seen.sum()),
    }
    if depth > 0:
        row["error_pct"] = 100 * float(diff) / depth
    else:
        row["error_mm"] = float(diff)
    return row


def imprint(repeats: int, quick: bool) -> list[dict]:
    rows = []
    subdivisions = SPHERE_SUBDIVISIONS[:3] if quick else SPHERE_SUBDIVISIONS
    cases = []
    for radius in (10.0, 50.0):
        for sub in subdivisions:
            cases.append(("sphere", radius, sub))
    for n_around in CYLINDER_AROUND[:2] if quick else CYLINDER_AROUND:
        cases.append(("cylinder", 30.0, n_around))
    for n in PLANE_GRIDS:
        cases.append(("plane", 0.0, n))
    for shape, radius, res in tqdm(cases, desc="imprint", leave=False):
        if shape == "sphere":
            model = primitives.sphere(radius, res)
            label = f"R{radius:g} s{res}"
            normal_kinds = ("interpolated", "face") if radius == 50.0 else ("interpolated",)

            def analytic(xy, r=radius):
                r2 = (xy**2).sum(axis=-1)
                return r - np.sqrt(np.maximum(r**2 - r2, 0.0)), r2 < r**2
        elif shape == "cylinder":
            model = primitives.cylinder(radius, 100.0, n_around=res, n_along=16)
            label = f"R{radius:g} n{res}"
            normal_kinds = ("interpolated",)

            def analytic(xy, r=radius):
                y2 = xy[..., 1] ** 2  # pad x runs along the axis, y across it
                return r - np.sqrt(np.maximum(r**2 - y2, 0.0)), y2 < r**2
        else:
            model = primitives.plane(100.0, res)
            label = f"{res}x{res}"
            normal_kinds = ("interpolated",)

            def analytic(xy):
                return np.zeros(xy.shape[:-1]), np.ones(xy.shape[:-1], bool)

        for normal in normal_kinds:
            if shape == "sphere":
                position, normals = _surface_pose(model, SPHERE_DIRECTION, normal)
            elif shape == "cylinder":  # on a vertex column (theta = 0)
                position, normals = np.array([[radius, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]])
            else:
                position, normals = np.array([[3.3, -2.1, 0.0]]), np.array([[0.0, 0.0, 1.0]])
            tangent = (
                np.array([[0.0, 0.0, 1.0]]) if shape == "cylinder" else np.cross(normals, [1.0, 0.0, 0.0])
            )
            for taxels in TAXELS if normal == "interpolated" else (32,):
                rows.append(
                    _imprint_row(
                        shape, label, model, taxels, normal, position, normals, tangent, analytic, repeats
                    )
                )
    return rows


# ------------------------------------------------------------------------------------ throughput
class _CountingScene:
    """Stands in for a RaycastingScene to count the rays ``press`` casts."""

    def __init__(self, scene):
        self.scene, self.rays = scene, 0

    def cast_rays(self, rays, **kwargs):
        self.rays += rays.shape[0]
        return self.scene.cast_rays(rays, **kwargs)


def _real_meshes(k: int) -> list[ObjectModel]:
    items = list_collection(DATA / "shrec07")
    # Spread over the classes: every (len / k)-th file.
    picks = [items[i] for i in np.linspace(0, len(items) - 1, k).round().astype(int)]
    return [load_object(path, label=label, name=f"{label}/{path.stem}") for path, label in picks]


def _random_contours(model: ObjectModel, n: int, rng: np.random.Generator):
    contours = []
    while len(contours) < n:
        i, j = rng.choice(model.n_vertices, 2, replace=False)
        with contextlib.suppress(ContourError):  # near-collinear draw: draw again
            contours.append(
                make_contour(model, plane_through(model.center, model.vertices[i], model.vertices[j]))
            )
    return contours


def stepwise_sides(sensor: FSRSensor, model: ObjectModel, positions, normals, tangents) -> np.ndarray:
    """Reference adaptive rule, one ladder step at a time: the first side from the top that does not
    penetrate (or min_side_mm). Costs up to one full cast per step."""
    ladder = np.unique(
        np.maximum(sensor.side_mm * sensor.shrink_factor ** np.arange(60.0), sensor.min_side_mm)
    )
    result = np.full(len(positions), sensor.min_side_mm)
    todo = np.arange(len(positions))
    for side in ladder[::-1]:
        gaps = sensor.measure_gaps(model, positions[todo], normals[todo], tangents[todo], side)
        fits = gaps.min(axis=(1, 2)) >= -sensor.penetration_eps_mm
        result[todo[fits]] = side
        todo = todo[~fits]
    return result


def throughput(models: list[ObjectModel], n_contours: int, repeats: int, seed: int) -> dict:
    rows = []
    sensor = FSRSensor()
    rng = np.random.default_rng(seed)
    for model in tqdm(models, desc="throughput", leave=False):
        contours = _random_contours(model, n_contours, rng)
        poses = [
            np.concatenate([getattr(c, name) for c in contours])
            for name in ("positions", "normals", "tangents")
        ]
        n_frames = len(poses[0])
        # The raw limit: the same probes' full-side rays, built once, cast on the same scene.
        grid = np.concatenate([sensor._unit_grid, np.ones((RAYS_PER_FRAME, 1))], axis=1)
        positions, normals, tangents = poses
        axes = np.stack(
            [
                tangents * sensor.side_mm,
                np.cross(normals, tangents) * sensor.side_mm,
                positions + sensor.standoff_mm * normals,
            ],
            axis=1,
        )
        rays = np.concatenate(
            [np.matmul(grid, axes), np.repeat(-normals[:, None, :], RAYS_PER_FRAME, axis=1)], axis=2
        )
        tensor = o3d.core.Tensor(rays.reshape(-1, 6).astype(np.float32))
        model.scene.cast_rays(tensor)  # warm-up
        sensor.press(model, *poses)
        ours, raw, fixed = [], [], []
        for _ in range(repeats):
            ours.append(median_time(partial(sensor.press, model, *poses), 1)[0])
            raw.append(median_time(partial(model.scene.cast_rays, tensor), 1)[0])
            fixed.append(median_time(partial(sensor.press, model, *poses, adaptive=False), 1)[0])
        counting = _CountingScene(model.scene)
        model.__dict__["scene"] = counting
        _, sides = sensor.press(model, *poses)
        model.__dict__["scene"] = counting.scene
        reference = stepwise_sides(sensor, model, *poses)
        t_ours, t_raw, t_fixed = (statistics.median(t) for t in (ours, raw, fixed))
        rows.append(
            {
                "mesh": model.name,
                "triangles": model.n_triangles,
                "frames": n_frames,
                "ours_fps": n_frames / t_ours,
                "raw_fps": n_frames / t_raw,
                "ratio": t_raw / t_ours,
                "fixed_pad_fps": n_frames / t_fixed,
                "fixed_ratio": t_raw / t_fixed,
                "rays_per_frame": counting.rays / n_frames,
                "shrunk": float((sides < sensor.side_mm).mean()),
                "mean_side_mm": float(sides.mean()),
                "t_ours_s": t_ours,
                "t_raw_s": t_raw,
                "same_side_as_stepwise": float(np.isclose(sides, reference).mean()),
            }
        )
    total = {
        "frames": sum(r["frames"] for r in rows),
        "ours_fps": sum(r["frames"] for r in rows) / sum(r["t_ours_s"] for r in rows),
        "raw_fps": sum(r["frames"] for r in rows) / sum(r["t_raw_s"] for r in rows),
    }
    total["ratio"] = total["ours_fps"] / total["raw_fps"]
    total["raw_mrays_per_s"] = total["raw_fps"] * RAYS_PER_FRAME / 1e6
    return {"rows": rows, "total": total}


# --------------------------------------------------------------------------------------- slicing
def _trimesh_section(mesh, plane):
    return mesh.section(plane_origin=plane.point, plane_normal=plane.normal)


def _slice_all(cut, mesh, planes) -> list:
    return [cut(mesh, plane) for plane in planes]


def slicing(models: list[ObjectModel], n_planes: int, repeats: int, seed: int) -> dict:
    try:
        import trimesh
    except ImportError:
        trimesh = None
    rng = np.random.default_rng(seed)
    rows = []
    for model in tqdm(models, desc="slicing", leave=False):
        planes = []
        while len(planes) < n_planes:
            i, j = rng.choice(model.n_vertices, 2, replace=False)
            with contextlib.suppress(ContourError):  # near-collinear draw: draw again
                planes.append(plane_through(model.center, model.vertices[i], model.vertices[j]))
        t_ours = median_time(partial(_slice_all, section_chains, model, planes), repeats)[0] / n_planes
        row = {"mesh": model.name, "triangles": model.n_triangles, "ours_ms": 1e3 * t_ours}
        if trimesh is not None:
            peer = trimesh.Trimesh(model.vertices, model.triangles, process=False)
            t_peer = median_time(partial(_slice_all, _trimesh_section, peer, planes), repeats)[0] / n_planes
            ours_len = [sum(c.length_mm for c in section_chains(model, p)) for p in planes]
            peer_len = [
                float(s.length) if (s := peer.section(plane_origin=p.point, plane_normal=p.normal)) else 0.0
                for p in planes
            ]
            diff = max(abs(a - b) / max(b, 1e-12) for a, b in zip(ours_len, peer_len))
            row.update({"trimesh_ms": 1e3 * t_peer, "speedup": t_peer / t_ours, "length_rel_diff": diff})
        rows.append(row)
    note = None if trimesh is not None else "trimesh is not installed: peer column skipped"
    return {"rows": rows, "note": note}


# ------------------------------------------------------------------------------------------- main
def _print_table(title: str, rows: list[dict], columns: list[tuple[str, str]]) -> None:
    print(f"\n{title}")
    widths = [max(len(head), 10) for head, _ in columns]
    print("  ".join(head.rjust(w) for (head, _), w in zip(columns, widths)))
    for row in rows:
        cells = []
        for (head, key), w in zip(columns, widths):
            value = row.get(key, "")
            if isinstance(value, float):
                value = f"{value:.4g}"
            cells.append(str(value).rjust(w))
        print("  ".join(cells))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.tactile", description=__doc__.split("\n")[0])
    parser.add_argument("--json", action="store_true", help="print a JSON result after the tables")
    parser.add_argument("--quick", action="store_true", help="fewer resolutions, meshes and repeats")
    parser.add_argument("--repeats", type=int, default=None, help="timing repeats (median)")
    parser.add_argument("--meshes", type=int, default=None, help="SHREC meshes for (b) and (c)")
    parser.add_argument("--contours", type=int, default=8, help="25-probe contours per mesh in (b)")
    parser.add_argument("--planes", type=int, default=20, help="planes per mesh in (c)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 7)
    n_meshes = args.meshes or (2 if args.quick else 5)

    result = {"machine": machine(), "imprint": imprint(repeats, args.quick)}
    _print_table(
        "(a) imprint error vs run time (one 20 mm pad; error in % of the analytic depth range)",
        result["imprint"],
        [
            ("shape", "shape"),
            ("mesh", "mesh"),
            ("triangles", "triangles"),
            ("taxels", "taxels"),
            ("normal", "normal"),
            ("error %", "error_pct"),
            ("error mm", "error_mm"),
            ("time ms", "time_ms"),
        ],
    )
    if (DATA / "shrec07").is_dir():
        models = _real_meshes(n_meshes)
        result["throughput"] = throughput(models, args.contours, repeats, args.seed)
        _print_table(
            "(b) press throughput, adaptive pads, vs raw cast_rays (1,024 rays/frame)",
            result["throughput"]["rows"] + [{"mesh": "ALL", **result["throughput"]["total"]}],
            [
                ("mesh", "mesh"),
                ("frames", "frames"),
                ("ours fr/s", "ours_fps"),
                ("raw fr/s", "raw_fps"),
                ("ratio", "ratio"),
                ("fixed fr/s", "fixed_pad_fps"),
                ("fixed ratio", "fixed_ratio"),
                ("rays/frame", "rays_per_frame"),
                ("shrunk", "shrunk"),
                ("side mm", "mean_side_mm"),
                ("= stepwise", "same_side_as_stepwise"),
            ],
        )
        result["slicing"] = slicing(models, args.planes, repeats, args.seed)
        _print_table(
            "(c) slicing time per plane, ours vs trimesh.section",
            result["slicing"]["rows"],
            [
                ("mesh", "mesh"),
                ("triangles", "triangles"),
                ("ours ms", "ours_ms"),
                ("trimesh ms", "trimesh_ms"),
                ("speedup", "speedup"),
                ("len rel diff", "length_rel_diff"),
            ],
        )
        if result["slicing"]["note"]:
            print(result["slicing"]["note"])
    else:
        result["note"] = f"{DATA / 'shrec07'} is absent: throughput and slicing skipped"
        print(result["note"])
    print(f"\nmachine: {result['machine']['platform']}, {result['machine']['cores_available']} of {result['machine']['cpu_count']} cores")
    if args.json:
        print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
