"""``visuotactile demo``: the whole pipeline on built-in objects (what ``make demo`` runs)."""

from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.demo import run_demo

    run_demo(Path(args.out), seed=args.seed)
    return 0


def register(sub) -> None:
    demo = sub.add_parser("demo", help="run the pipeline on built-in objects and write figures")
    demo.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=run)
