"""``visuotactile bench NAME [options]``: run ``benchmarks/NAME.py`` (its options, e.g. ``--json``, pass on)."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import benchmarks


def available_benchmarks() -> list[str]:
    """Names of the modules in ``benchmarks/`` that define ``main``."""
    return sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if not m.name.startswith("_"))


def run(args: argparse.Namespace, rest: list[str]) -> int:
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


def register(sub) -> None:
    # No help flag of its own: `bench NAME --help` reaches the benchmark's parser.
    bench = sub.add_parser(
        "bench", add_help=False, help="run a benchmark from benchmarks/ (extra arguments, e.g. --json, are passed on)"
    )
    bench.add_argument("name", nargs="?", help=f"one of: {', '.join(available_benchmarks())}")
    bench.set_defaults(func=run, passes_extra_args=True)
