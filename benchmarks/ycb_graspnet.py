"""Real capture, real objects: name the YCB objects of the GraspNet tabletop frame by touching their single-view
reconstructions, with classifiers trained on the 16 YCB meshes alone (issue: recognition in the robot's world).

Training (``../shared/data/ycb``, physical millimetres, pose-free frame): each mesh upright (its CAD surface) and
``--captures`` virtual single-view OAK-D reconstructions of it lying on a table (what one camera view of it gives:
the far side closed against the table and the carved space), ``--contours`` blind contours each. A capture sets
the mesh down in a seeded stable resting pose (``--poses resting``: dropped on the table, it rolls onto a face
that holds it; ``random``: a uniformly random rotation, lowest point on the table) and looks at it from an
elevation and distance drawn uniformly from ``--elevation`` and ``--distance`` (what a tabletop robot's camera
sees), reconstructed with the settings of the real frame's reconstruction (``--settings real``:
``fusion.camera.REAL_RECONSTRUCTION``, flying pixels dropped) or of virtual captures (``virtual``). Nothing of
the GraspNet frame is used for training.

Validation (``--validation N``; the real frame is then not read): N held-out virtual captures of each YCB mesh at
the real camera's geometry (elevation 55-80 degrees, distance 430-560 mm, measured on the frame's table plane
and annotated poses), in stable resting poses with seeds disjoint from training, reconstructed as the real frame
is and touched along ``--touches`` blind contours: top-1 and top-3 accuracy over the 16 classes and over the four
classes of the frame. The settings are chosen there, never on the real frame.

Test: the real RealSense frame (``../shared/data/rgbd/graspnet_tabletop``). Each of the four YCB objects there
(cracker box, tomato soup can, banana, power drill) is picked at the pixel of its annotated pose (the pose's
translation projected through the intrinsics: what ``visuotactile camera --target U,V`` does), reconstructed from
that one view at physical size, touched along ``--touches`` blind contours, and named by the sum of
log-probabilities; the table gives each classifier's top three classes per object.

    .venv/bin/python -m benchmarks.ycb_graspnet [--captures 8] [--contours 16] [--touches 8] [--kinds knn,svm,cnn]
        [--elevation 30,80] [--distance 400,700] [--poses resting] [--settings real] [--validation N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from benchmarks._common import DATA, machine

#: GraspNet object id -> YCB mesh stem (the four YCB objects of the frame that the shared YCB folder holds).
TARGETS = {0: "003_cracker_box", 2: "005_tomato_soup_can", 5: "011_banana", 8: "035_power_drill"}
KINDS = ("knn", "svm", "cnn")
POSES = ("resting", "random")
SETTINGS = ("real", "virtual")
#: The real frame's camera, measured on its table plane and the annotated poses of the four objects: 464 mm
#: above the table, 436-538 mm from the objects, 57-79 degrees above the table. The validation captures look
#: from there.
VALIDATION_ELEVATION_DEG = (55.0, 80.0)
VALIDATION_DISTANCE_MM = (430.0, 560.0)
#: Seeds of the validation captures start here (training captures take seed + 1000 i + 1 ... + captures).
VALIDATION_SEED = 1_000_000


def class_of(stem: str) -> str:
    """'003_cracker_box' -> 'cracker_box'."""
    return stem.split("_", 1)[1]


def ycb_models() -> list:
    """The 16 YCB meshes at physical size (the files are in metres), centred in the pose-free frame."""
    from perception.geometry import load_object, rescale

    models = []
    for path in sorted((DATA / "ycb").glob("*.obj")):
        raw = load_object(path, size_mm=None)
        model = rescale(raw, 1000.0 * raw.size, name=path.stem)
        model.label = class_of(path.stem)
        models.append(model)
    return models


def reconstruction_settings(settings: str) -> dict:
    """``"real"`` or ``"virtual"`` -> the reconstruction settings of that kind of camera (fusion.camera)."""
    from fusion.camera import REAL_RECONSTRUCTION, VIRTUAL_RECONSTRUCTION

    return dict(REAL_RECONSTRUCTION if settings == "real" else VIRTUAL_RECONSTRUCTION)


def capture_sequences(model, pose_seed: int, contours: int, *, elevation_deg=(35.0, 35.0),
                      distance_mm=(500.0, 500.0), poses: str = "random", settings: str | None = None,
                      name: str | None = None):
    """Blind sequences of one virtual single-view reconstruction of ``model`` (physical size) set on a table in a
    pose seeded by ``pose_seed`` (:data:`POSES`), seen from an elevation and distance drawn uniformly from the
    (low, high) ranges (a range of one value: that value, nothing drawn); returns (sequences, capture seconds,
    reconstruction size mm). ``settings=None`` keeps ``virtual_capture``'s reconstruction defaults.

    Raises:
        VisuotactileError: the reconstruction fails.
    """
    from perception.geometry import random_rotation, rescale, rotate
    from tactile import touch
    from tactile.captures import resting_rotation, virtual_capture

    rotation = resting_rotation(model, pose_seed) if poses == "resting" else random_rotation(pose_seed)
    turned = rotate(model, rotation)
    rng = np.random.default_rng([pose_seed, 35])  # uniform(a, a) is exactly a: a one-value range draws nothing new
    view = {"elevation_deg": float(rng.uniform(*elevation_deg)), "distance_mm": float(rng.uniform(*distance_mm))}
    reconstruct = reconstruction_settings(settings) if settings else None
    cap = virtual_capture(turned, views=1, size_mm=turned.size, seed=pose_seed, reconstruct=reconstruct, **view)
    world = cap.world
    physical = rescale(world, world.size, name=name or f"{model.name}@capture")
    physical.label = model.label
    return touch(physical, "blind", contours, seed=pose_seed), cap.seconds, float(world.size)


def training_sequences(models, captures: int, contours: int, seed: int, log=print, *, elevation_deg=(35.0, 35.0),
                       distance_mm=(500.0, 500.0), poses: str = "random", settings: str | None = None,
                       cad: bool = True) -> tuple[list, dict]:
    """Blind sequences of every mesh upright (``cad``) and of ``captures`` single-view reconstructions of it
    (:func:`capture_sequences`); returns the sequences and the capture statistics."""
    from perception.errors import VisuotactileError
    from tactile import touch

    sequences, seconds, failed = [], [], []
    for i, model in enumerate(models):
        if cad:
            sequences += touch(model, "blind", contours, seed=seed + 1000 * i)
        for r in range(captures):
            pose_seed = seed + 1000 * i + r + 1
            try:
                seqs, sec, _ = capture_sequences(model, pose_seed, contours, elevation_deg=elevation_deg,
                                                 distance_mm=distance_mm, poses=poses, settings=settings,
                                                 name=f"{model.name}@capture{r}")
            except VisuotactileError as exc:  # a reconstruction that fails is left out and counted
                failed.append(f"{model.name} pose {r}: {type(exc).__name__}: {exc}")
                continue
            seconds.append(sec)
            sequences += seqs
        log(f"  {model.name}: {len(sequences)} sequences so far")
    return sequences, {"captures": len(seconds), "failed": failed,
                       "median_capture_s": float(np.median(seconds)) if seconds else None}


def validation_objects(models, n: int, touches: int, seed: int, log=print) -> list[dict]:
    """``n`` held-out virtual captures of each mesh at the real camera's geometry (:data:`VALIDATION_ELEVATION_DEG`,
    :data:`VALIDATION_DISTANCE_MM`), resting poses, seeds from :data:`VALIDATION_SEED`, reconstructed as the
    real frame is, ``touches`` blind touches each."""
    from perception.errors import VisuotactileError

    out = []
    for i, model in enumerate(models):
        for r in range(n):
            pose_seed = VALIDATION_SEED + seed + 1000 * i + r
            try:
                seqs, _, size = capture_sequences(model, pose_seed, touches, elevation_deg=VALIDATION_ELEVATION_DEG,
                                                  distance_mm=VALIDATION_DISTANCE_MM, poses="resting",
                                                  settings="real", name=f"{model.name}@validation{r}")
            except VisuotactileError as exc:
                log(f"  {model.name} validation {r}: {type(exc).__name__}: {exc} (left out)")
                continue
            out.append({"object": model.label, "capture": r, "size_mm": round(size, 1), "sequences": seqs})
        log(f"  {model.name}: {len(out)} validation captures so far")
    return out


def rank(fitted: dict, objects: list[dict], classes: list[str]) -> list[dict]:
    """Each object's row with each classifier's top three (class, fused log-probability) and whether the first is
    right; the objects' sequences are used up."""
    from fusion.decide import fuse_touches
    from tactile.explore import SequenceBatch

    rows = []
    for obj in objects:
        test = SequenceBatch.from_sequences(obj.pop("sequences"), class_names=classes)
        row = dict(obj)
        for kind, clf in fitted.items():
            names = [str(c) for c in clf.classes_]
            fused = fuse_touches(clf.predict_proba(test), rule="log")
            top = np.argsort(-fused, kind="stable")[:3]
            row[kind] = [(names[i], round(float(fused[i]), 3)) for i in top]
            row[f"{kind}_right"] = names[top[0]] == obj["object"]
            row[f"{kind}_top3"] = obj["object"] in [names[i] for i in top]
        rows.append(row)
    return rows


def validation_summary(rows: list[dict], kinds) -> dict:
    """Top-1 and top-3 accuracy per classifier, over all validation captures and over the frame's four classes."""
    targets = {class_of(stem) for stem in TARGETS.values()}
    out = {}
    for kind in kinds:
        entry = {}
        for scope, subset in (("all", rows), ("frame_classes", [r for r in rows if r["object"] in targets])):
            n = len(subset)
            entry[scope] = {"n": n, "top1": int(sum(r[f"{kind}_right"] for r in subset)),
                            "top3": int(sum(r[f"{kind}_top3"] for r in subset))}
        entry["per_class_top1"] = {c: int(sum(r[f"{kind}_right"] for r in rows if r["object"] == c))
                                   for c in sorted({r["object"] for r in rows})}
        out[kind] = entry
    return out


def fit(kind: str, batch, seed: int):
    from fusion.classifiers import make_classifier

    options = {"progress": False} if kind == "cnn" else {}
    return make_classifier(kind, random_state=seed, **options).fit(batch)


def real_objects(touches: int, seed: int) -> list[dict]:
    """Each target object of the GraspNet frame: picked by its annotated pixel, reconstructed from the one view
    at physical size, touched along ``touches`` blind contours."""
    from scipy.io import loadmat

    from fusion.camera import reconstruct_capture
    from perception.camera import read_recording
    from perception.geometry import rescale
    from tactile import touch

    folder = DATA / "rgbd" / "graspnet_tabletop"
    frames = read_recording(folder)
    meta = loadmat(folder / "meta.mat")
    origins = meta["poses"][:, 3, :].T * 1000.0
    ids = (meta["cls_indexes"][0] - 1).tolist()
    k = frames[0].intrinsics
    out = []
    for gid, stem in TARGETS.items():
        x, y, z = origins[ids.index(gid)]
        pixel = (float(np.rint(k.fx * x / z + k.cx)), float(np.rint(k.fy * y / z + k.cy)))
        start = time.perf_counter()
        rec = reconstruct_capture(frames, virtual=False, target_pixel=pixel, name=stem, seed=seed)
        model = rescale(rec.model, rec.model.size, name=stem)
        sequences = touch(model, "blind", touches, seed=seed)
        out.append({"object": class_of(stem), "graspnet_id": gid, "pixel": f"{pixel[0]:.0f},{pixel[1]:.0f}",
                    "size_mm": round(model.size, 1), "warnings": list(rec.warnings),
                    "seconds": round(time.perf_counter() - start, 1), "sequences": sequences})
    return out


def _range(text: str, name: str) -> tuple[float, float]:
    parts = [float(x) for x in text.split(",")]
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or not parts[0] <= parts[1]:
        raise argparse.ArgumentTypeError(f"{name}: expected LOW,HIGH or one value, got {text!r}")
    return parts[0], parts[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.ycb_graspnet", description=__doc__.split("\n\n")[0])
    parser.add_argument("--captures", type=int, default=8, help="single-view captures per YCB mesh for training")
    parser.add_argument("--contours", type=int, default=16, help="blind contours per training object")
    parser.add_argument("--touches", type=int, default=8, help="blind touches per real (or validation) object")
    parser.add_argument("--elevation", default="30,80",
                        help="camera elevation of the training captures, degrees: LOW,HIGH drawn uniformly, or one value")
    parser.add_argument("--distance", default="400,700",
                        help="camera distance of the training captures, mm: LOW,HIGH drawn uniformly, or one value")
    parser.add_argument("--poses", choices=POSES, default="resting", help="how the training meshes lie on the table")
    parser.add_argument("--settings", choices=SETTINGS, default="real",
                        help="reconstruction settings of the training captures (those of a real or a virtual camera)")
    parser.add_argument("--no-cad", action="store_true", help="leave the upright CAD meshes out of training")
    parser.add_argument("--validation", type=int, default=0, metavar="N",
                        help="instead of the real frame: N held-out virtual captures per mesh at the real camera's "
                             "geometry")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", default=",".join(KINDS), help="classifiers to fit, comma-separated (default all)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    args = parser.parse_args(argv)
    kinds = tuple(k for k in args.kinds.split(",") if k)
    if not kinds or set(kinds) - set(KINDS):
        parser.error(f"--kinds: choose from {', '.join(KINDS)}")
    try:
        elevation, distance = _range(args.elevation, "--elevation"), _range(args.distance, "--distance")
    except (ValueError, argparse.ArgumentTypeError) as exc:
        parser.error(str(exc))
    if not (0 < elevation[0] and elevation[1] < 90) or distance[0] <= 0:
        parser.error("--elevation must lie in (0, 90) degrees and --distance be positive")
    if args.validation < 0 or args.captures < 0 or args.captures >= 1000:
        parser.error("--validation must be >= 0 and --captures in 0..999")
    if not (DATA / "ycb").is_dir() or not (DATA / "rgbd" / "graspnet_tabletop").is_dir():
        print(f"the shared data ({DATA}/ycb and rgbd/graspnet_tabletop) is absent", file=sys.stderr)
        return 2
    from tactile.explore import SequenceBatch

    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    start = time.perf_counter()
    models = ycb_models()
    classes = sorted({m.label for m in models})
    train, capture_stats = training_sequences(models, args.captures, args.contours, args.seed, log,
                                              elevation_deg=elevation, distance_mm=distance, poses=args.poses,
                                              settings=args.settings, cad=not args.no_cad)
    batch = SequenceBatch.from_sequences(train, class_names=classes)
    log(f"training: {len(batch)} sequences of {len(classes)} classes; capture stats {capture_stats}")
    fitted = {kind: fit(kind, batch, args.seed) for kind in kinds}
    settings = {"captures": args.captures, "contours": args.contours, "touches": args.touches,
                "elevation_deg": list(elevation), "distance_mm": list(distance), "poses": args.poses,
                "settings": args.settings, "cad": not args.no_cad, "seed": args.seed}
    if args.validation:
        objects = validation_objects(models, args.validation, args.touches, args.seed, log)
        rows = rank(fitted, objects, classes)
        summary = validation_summary(rows, kinds)
        result = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "mode": "validation", **settings,
                  "validation_per_mesh": args.validation, "validation_elevation_deg": list(VALIDATION_ELEVATION_DEG),
                  "validation_distance_mm": list(VALIDATION_DISTANCE_MM), "training_sequences": len(batch),
                  "capture_stats": capture_stats, "summary": summary,
                  "objects": [{k: v for k, v in r.items() if not k.endswith(("_right", "_top3"))} for r in rows],
                  "seconds": round(time.perf_counter() - start, 1)}
        if args.json:
            print(json.dumps(result, indent=2))
            return 0
        print(f"\nValidation: {len(rows)} held-out virtual single-view captures of the {len(classes)} YCB meshes "
              f"(elevation {VALIDATION_ELEVATION_DEG[0]:.0f}-{VALIDATION_ELEVATION_DEG[1]:.0f} deg, distance "
              f"{VALIDATION_DISTANCE_MM[0]:.0f}-{VALIDATION_DISTANCE_MM[1]:.0f} mm, resting poses, real "
              f"reconstruction settings), {args.touches} blind touches, log rule")
        print(f"{'classifier':<12}{'top-1 all':>14}{'top-3 all':>14}{'top-1 frame 4':>16}{'top-3 frame 4':>16}")
        for kind, e in summary.items():
            a, f = e["all"], e["frame_classes"]
            print(f"{kind:<12}{a['top1']:>8}/{a['n']:<5}{a['top3']:>8}/{a['n']:<5}{f['top1']:>10}/{f['n']:<5}"
                  f"{f['top3']:>10}/{f['n']:<5}")
        print("top-1 per class: " + "; ".join(
            f"{c} " + "/".join(str(summary[k]["per_class_top1"][c]) for k in kinds) for c in classes))
        print(f"({time.perf_counter() - start:.0f} s)")
        return 0
    objects = real_objects(args.touches, args.seed)
    rows = rank(fitted, objects, classes)
    result = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "mode": "real", **settings,
              "training_sequences": len(batch), "capture_stats": capture_stats,
              "objects": [{k: v for k, v in r.items() if not k.endswith("_top3")} for r in rows],
              "right": {kind: int(sum(r[f"{kind}_right"] for r in rows)) for kind in kinds},
              "seconds": round(time.perf_counter() - start, 1)}
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"\nYCB objects of the GraspNet frame, named among {len(classes)} YCB classes ({args.touches} blind "
          f"touches, log rule); trained on the YCB meshes and {args.captures} virtual single-view captures each")
    print(f"{'object':<18}{'size mm':>9}  " + "  ".join(f"{k:<48}" for k in kinds))
    for r in rows:
        cells = ["; ".join(f"{n} {p:.2f}" for n, p in r[k]) for k in kinds]
        print(f"{r['object']:<18}{r['size_mm']:>9.0f}  " + "  ".join(f"{c:<48}" for c in cells))
    print("right (top 1): " + ", ".join(f"{k} {result['right'][k]} of {len(rows)}" for k in kinds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
