"""``visuotactile demo``: the whole pipeline on built-in objects, recognition included (what ``make demo`` runs)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from fusion.commands import positive_int


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.commands import print_json
    from fusion.demo import DEMO_SIZES, check_demo_sizes, run_demo
    from perception.atomic import check_output_folder

    changes = {k: v for k, v in (("objects_per_class", args.objects_per_class), ("unseen_contours", args.contours),
                                 ("epochs", args.epochs)) if v is not None}  # Sizes refuses epochs < 1
    sizes = check_demo_sizes(replace(DEMO_SIZES, **changes))
    check_output_folder(args.out, "--out")
    echo = (lambda line: print(line, file=sys.stderr)) if args.json else print
    summary = run_demo(Path(args.out), seed=args.seed, sizes=sizes,
                       recognition=not args.no_recognition, echo=echo)
    if args.json:
        print_json(summary)
    return 0


def register(sub) -> None:
    demo = sub.add_parser("demo", help="recognize built-in objects by touch, end to end (report, figures, models)")
    demo.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    demo.add_argument("--seed", type=int, default=0, help="seed of objects, data, splits and models (default 0)")
    demo.add_argument("--objects-per-class", type=positive_int, help="built-in instances per class (default 3)")
    demo.add_argument("--contours", type=positive_int, help="contours per object and strategy (default 30)")
    demo.add_argument("--epochs", type=positive_int, help="CNN epochs at most (default 12)")
    demo.add_argument("--no-recognition", action="store_true", help="only the catalogue, saliency and touch figures")
    demo.add_argument("--json", action="store_true", help="print summary.json on stdout (tables go to stderr)")
    demo.set_defaults(func=run)
