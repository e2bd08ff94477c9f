"""The ``visuotactile`` command line: ``demo`` and ``bench NAME``.

Each subcommand is a thin layer over the library; ``bench NAME`` runs ``benchmarks/NAME.py``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
from pathlib import Path

import benchmarks

log = logging.getLogger(__name__)


def available_benchmarks() -> list[str]:
    """Names of the modules in ``benchmarks/`` that define ``main``."""
    return sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if not m.name.startswith("_"))


def _bench(args: argparse.Namespace, rest: list[str]) -> int:
    names = available_benchmarks()
    if args.name is None:
        print(f"usage: visuotactile bench NAME [options]; NAME is one of: {', '.join(names)}; "
              "`visuotactile bench NAME --help` lists its options")
        return 0 if {"-h", "--help"} & set(rest) else 2
    if args.name not in names:
        print(f"unknown benchmark {args.name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"benchmarks.{args.name}")
    return int(module.main(rest) or 0)


def _demo(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.demo import run_demo

    run_demo(Path(args.out), seed=args.seed)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="visuotactile", description="Visually guided tactile object recognition toolkit."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the pipeline on built-in objects and write figures")
    demo.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)

    # No help flag of its own: `bench NAME --help` reaches the benchmark's parser.
    bench = sub.add_parser(
        "bench", add_help=False, help="run a benchmark from benchmarks/ (extra arguments, e.g. --json, are passed on)"
    )
    bench.add_argument("name", nargs="?", help=f"one of: {', '.join(available_benchmarks())}")
    bench.set_defaults(func=_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if rest and args.command != "bench":
        parser.error(f"unrecognised arguments: {' '.join(rest)}")
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return args.func(args, rest)


if __name__ == "__main__":
    sys.exit(main())
