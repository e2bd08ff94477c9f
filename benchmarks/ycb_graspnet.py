"""Real capture, real objects: name the YCB objects of the GraspNet tabletop frame by touching their single-view
reconstructions, with classifiers trained on the 16 YCB meshes alone (issue: recognition in the robot's world).

Training (``../shared/data/ycb``, physical millimetres, pose-free frame): each mesh upright (its CAD surface) and
``--captures`` virtual single-view OAK-D reconstructions of it lying in seeded random poses on a table (what one
camera view of it gives: the far side closed against the table and the carved space), ``--contours`` blind
contours each. Nothing of the GraspNet frame is used for training.

Test: the real RealSense frame (``../shared/data/rgbd/graspnet_tabletop``). Each of the four YCB objects there
(cracker box, tomato soup can, banana, power drill) is picked at the pixel of its annotated pose (the pose's
translation projected through the intrinsics: what ``visuotactile camera --target U,V`` does), reconstructed from
that one view at physical size, touched along ``--touches`` blind contours, and named by the sum of
log-probabilities; the table gives each classifier's top three classes per object.

    .venv/bin/python -m benchmarks.ycb_graspnet [--captures 6] [--contours 24] [--touches 8] [--kinds knn,svm,cnn] [--json]
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


def training_sequences(models, captures: int, contours: int, seed: int, log=print) -> tuple[list, dict]:
    """Blind sequences of every mesh upright and of ``captures`` single-view reconstructions of it in random
    poses; returns the sequences and the capture statistics."""
    from perception.errors import VisuotactileError
    from perception.geometry import random_rotation, rescale, rotate
    from tactile import touch
    from tactile.captures import virtual_capture

    sequences, seconds, failed = [], [], []
    for i, model in enumerate(models):
        sequences += touch(model, "blind", contours, seed=seed + 1000 * i)
        for r in range(captures):
            pose_seed = seed + 1000 * i + r + 1
            turned = rotate(model, random_rotation(pose_seed))
            try:
                cap = virtual_capture(turned, views=1, size_mm=turned.size, seed=pose_seed)
            except VisuotactileError as exc:  # a reconstruction that fails is left out and counted
                failed.append(f"{model.name} pose {r}: {type(exc).__name__}: {exc}")
                continue
            seconds.append(cap.seconds)
            world = cap.world
            physical = rescale(world, world.size, name=f"{model.name}@capture{r}")
            physical.label = model.label
            sequences += touch(physical, "blind", contours, seed=pose_seed)
        log(f"  {model.name}: {len(sequences)} sequences so far")
    return sequences, {"captures": len(seconds), "failed": failed,
                       "median_capture_s": float(np.median(seconds)) if seconds else None}


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks.ycb_graspnet", description=__doc__.split("\n\n")[0])
    parser.add_argument("--captures", type=int, default=6, help="single-view captures per YCB mesh for training")
    parser.add_argument("--contours", type=int, default=24, help="blind contours per training object")
    parser.add_argument("--touches", type=int, default=8, help="blind touches per real object")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--kinds", default=",".join(KINDS), help="classifiers to fit, comma-separated (default all)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    args = parser.parse_args(argv)
    kinds = tuple(k for k in args.kinds.split(",") if k)
    if not kinds or set(kinds) - set(KINDS):
        parser.error(f"--kinds: choose from {', '.join(KINDS)}")
    if not (DATA / "ycb").is_dir() or not (DATA / "rgbd" / "graspnet_tabletop").is_dir():
        print(f"the shared data ({DATA}/ycb and rgbd/graspnet_tabletop) is absent", file=sys.stderr)
        return 2
    from fusion.decide import fuse_touches
    from tactile.explore import SequenceBatch

    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    start = time.perf_counter()
    models = ycb_models()
    classes = sorted({m.label for m in models})
    train, capture_stats = training_sequences(models, args.captures, args.contours, args.seed, log)
    batch = SequenceBatch.from_sequences(train, class_names=classes)
    log(f"training: {len(batch)} sequences of {len(classes)} classes; capture stats {capture_stats}")
    fitted = {kind: fit(kind, batch, args.seed) for kind in kinds}
    objects = real_objects(args.touches, args.seed)
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
        rows.append(row)
    result = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "captures": args.captures,
              "contours": args.contours, "touches": args.touches, "seed": args.seed, "training_sequences": len(batch),
              "capture_stats": capture_stats, "objects": rows,
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
