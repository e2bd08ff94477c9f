"""``visuotactile recognize MESH``: touch a mesh file along K contours and name its class."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fusion.commands import positive_int
from fusion.commands.evaluate import check_figure

DEFAULT_MODEL = "out/demo/models/cnn.vtm"


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.commands import print_json
    from fusion.experiments.recognize import plot_recognition, recognize_file
    from perception.limits import check_count

    check_count("touches", args.touches, "--touches")  # before the model and the mesh load
    if args.figure is not None:
        check_figure(args.figure)

    obj, result = recognize_file(args.mesh, args.model, touches=args.touches, strategy=args.strategy, seed=args.seed,
                                 rule=args.rule, trust_pickle=args.trust_pickle)
    out = {"mesh": str(args.mesh), "model": str(Path(args.model)), "touches": args.touches, "strategy": args.strategy,
           "seed": args.seed, **result.to_dict()}
    if args.figure:
        out["figure"] = str(plot_recognition(obj, result, args.figure))
    if args.json:
        print_json(out)
        return 0
    print(f"{obj.name}: {result.summary()} after {args.touches} {args.strategy} touches")
    for name, p in list(result.probabilities.items())[:5]:
        print(f"  {name:<20} {100 * p:6.2f} %")
    seconds = result.seconds
    print(f"time: saliency {seconds['saliency']:.2f} s, touching {seconds['touching']:.2f} s, "
          f"inference {seconds['inference']:.3f} s", file=sys.stderr)
    if args.figure:
        print(f"figure: {out['figure']}")
    return 0


def register(sub) -> None:
    parser = sub.add_parser("recognize", help="recognize a mesh file by touch (class, probabilities, contours)",
                            description="Touch a mesh (OFF, OBJ, PLY, STL) along K contours with the model's "
                                        "sensor and fuse the K decisions (sum of log probabilities).")
    parser.add_argument("mesh", help="the mesh file")
    parser.add_argument("--model", default=DEFAULT_MODEL,
                        help=f"a model from `visuotactile train` or the demo (default: {DEFAULT_MODEL})")
    parser.add_argument("--trust-pickle", action="store_true",
                        help="also load an old pickled model (runs code from the file: only for files you made)")
    parser.add_argument("--touches", "-k", type=positive_int, default=4, help="contours per decision K (default 4)")
    parser.add_argument("--strategy", default="guided",
                        help="where to touch: a key of tactile.sampling.STRATEGIES, e.g. blind, guided (multiview "
                             "saliency), mesh, iss, pcl_harris, pcl_iss (PCL keypoints: `make peers` first) "
                             "(default: guided)")
    parser.add_argument("--rule", choices=("log", "sum", "tempered"), default=None,
                        help="fusion of the K touches (default: tempered log rule for a calibrated model, "
                             "answering 'unknown' when the touches fit no known class; else log: sum of log "
                             "probabilities)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the contour choice (default 0)")
    parser.add_argument("--figure", help="write the touched contours and probabilities to this PNG (or .pdf, .svg)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    parser.set_defaults(func=run)
