"""``visuotactile camera``: recognize an object from an RGB-D capture (virtual OAK, live OAK or a recording);
the pipeline is :func:`fusion.camera.recognize_capture`."""

from __future__ import annotations

import argparse
import os

import numpy as np

from fusion.commands import positive_int
from perception.errors import InvalidArgumentError

#: Largest --seed (checked with the others in :func:`fusion.cli.check_common`): the seed reaches
#: ``o3d.utility.random.seed``, a C int, so larger seeds are refused rather than folded onto smaller ones.
SEED_MAX = 2**31 - 1


def parse_pixel(text: str) -> tuple[float, float]:
    """``"U,V"`` (column, row of the first frame) -> (u, v).

    Raises:
        InvalidArgumentError: not two finite numbers separated by a comma (the image bounds are checked
            where the frame is known, :func:`perception.reconstruct.tabletop.pixel_point`).
    """
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        u, v = float(parts[0]), float(parts[1])
        if not (np.isfinite(u) and np.isfinite(v)):
            raise ValueError
    except ValueError:
        raise InvalidArgumentError(f"--target {text!r}: expected a pixel U,V (column,row), e.g. --target 640,360") from None
    return u, v


def check_camera_args(args: argparse.Namespace) -> None:
    """What can be checked before a capture: counts within their limits, the strategy, the output folder, and the
    model file (loaded once here, so a bad file is refused before the camera runs).

    Raises:
        InvalidArgumentError, ModelFileError: naming the option and the problem.
    """
    from perception.atomic import check_output_folder
    from perception.camera.frame import MAX_DISTANCE_MM
    from perception.limits import check_count

    if args.contours < 1:
        raise InvalidArgumentError(f"--contours must be at least 1, got {args.contours}")
    check_count("contours", args.contours, "--contours")
    if args.views < 1:
        raise InvalidArgumentError(f"--views must be at least 1, got {args.views}")
    check_count("views", args.views, "--views")
    if not (np.isfinite(args.distance) and 0 < args.distance <= MAX_DISTANCE_MM):
        raise InvalidArgumentError(f"--distance must be a positive number of mm up to {MAX_DISTANCE_MM:g} "
                                   f"(the virtual camera's range), got {args.distance}")
    if args.source == "oak":
        return  # the device check comes first (seconds, without loading the geometry stack); a live capture is quick
    from tactile.sampling import STRATEGIES

    if args.strategy not in STRATEGIES:
        raise InvalidArgumentError(f"unknown --strategy {args.strategy!r}; choose one of {', '.join(STRATEGIES)}")
    if args.out is not None:
        check_output_folder(args.out, "--out")
    if args.model is not None:
        from fusion.base import load_model

        load_model(args.model, trust_pickle=args.trust_pickle)


def run(args: argparse.Namespace, rest: list[str]) -> int:
    if args.json:  # depthai's logger writes to stdout (e.g. "USB protocol not available" on import): JSON only there
        os.environ.setdefault("DEPTHAI_LEVEL", "error")
    from fusion.camera import recognize_capture
    from fusion.commands import print_json

    pixel = parse_pixel(args.target) if args.target is not None else None
    check_camera_args(args)
    summary = recognize_capture(
        args.source, views=args.views, distance_mm=args.distance, model_path=args.model, contours=args.contours,
        strategy=args.strategy, seed=args.seed, out=args.out, target_pixel=pixel, trust_pickle=args.trust_pickle,
    )
    if args.json:
        print_json(summary)
        return 0
    rec = summary["reconstruction"]
    print(f"source {summary['source']}: {summary['frames']} frame(s), {summary['objects_in_first_view']} object(s) "
          f"in the first view, {summary['object_points']} object points")
    for o in summary["objects"]:
        mark = "*" if o["index"] == summary["picked"]["index"] else " "
        pixel = "-" if o["pixel"] is None else f"({o['pixel'][0]:.0f}, {o['pixel'][1]:.0f})"
        print(f" {mark} object {o['index']:2d}: centre {o['center_mm']} mm, size {o['size_mm']} mm, pixel {pixel}")
    picked = summary["picked"]
    print(f"picked object {picked['index']}: size {picked['size_mm']} mm (diagonal {picked['diagonal_mm']:.0f} mm)")
    for w in summary["warnings"]:
        print(f"warning: {w}")
    line = f"reconstruction: {rec['vertices']} vertices, {rec['triangles']} triangles, {rec['diagonal_mm']:.1f} mm"
    if "error_mm" in rec:
        err = rec["error_mm"]
        line += f", error to the true mesh mean {err['mean_mm']:.2f} mm, p95 {err['p95_mm']:.2f} mm"
    print(line)
    print(f"touched: {summary['sequences']} contours x {summary['probes']} probes")
    if summary["prediction"] is None:
        print("no --model given: recognition skipped (train one with `visuotactile train`)")
    else:
        pred = summary["prediction"]
        if pred.get("unknown"):
            print(f"recognized: unknown; closest: {pred['closest']}, {pred['probabilities'][pred['closest']]:.2f}")
        else:
            print(f"recognized: {pred['class']}")
        for name, p in pred["probabilities"].items():
            print(f"  {name:12s} {p:.3f}")
    if "figure" in summary:
        print(f"figure: {summary['figure']}")
    return 0


def register(sub) -> None:
    camera = sub.add_parser(
        "camera", help="recognize an object from an RGB-D capture (virtual OAK, live OAK, or a recording folder)"
    )
    camera.add_argument(
        "--source", required=True,
        help="virtual:<class>[/<instance seed>] (simulated OAK-D), oak (live camera), or a recording folder",
    )
    camera.add_argument("--views", type=positive_int, default=4, help="views of the virtual OAK around the object (default 4)")
    camera.add_argument("--distance", type=float, default=500.0, help="virtual camera distance, mm (default 500)")
    camera.add_argument("--model", default=None, help="a trained classifier (visuotactile train); without it, no class")
    camera.add_argument("--trust-pickle", action="store_true",
                        help="also load an old pickled --model (runs code from the file: only for files you made)")
    camera.add_argument("--contours", type=positive_int, default=8, help="contours touched (default 8)")
    camera.add_argument("--strategy", default="blind", help="contour strategy: blind | guided | mesh | iss")
    camera.add_argument("--target", default=None, metavar="U,V",
                        help="touch the object this pixel (column,row) of the first frame shows (default: the one in front)")
    camera.add_argument("--seed", type=int, default=0,
                        help=f"seed of the virtual object, its noise and the reconstruction, 0 to {SEED_MAX} "
                             "(Open3D's seed is a C int: 31 bits) (default 0)")
    camera.add_argument("--json", action="store_true", help="print the summary as JSON")
    camera.add_argument("--out", default="out/camera", help="folder for the figure and summary.json")
    camera.set_defaults(func=run, seed_max=SEED_MAX)
