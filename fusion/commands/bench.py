"""``visuotactile bench NAME [options]``: run ``benchmarks/NAME.py`` of the checkout (its options, e.g. ``--json``,
pass on).

The benchmarks are not installed with the package (``benchmarks`` is a generic name in site-packages); they run
from a checkout of the repository, as ``python -m benchmarks.NAME`` from its root or through this command, which
finds them beside the installed (editable) packages.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from types import ModuleType

#: What to say when the benchmarks are not there (a wheel install).
NOT_PRESENT = ("the benchmarks are not installed with the package: run them from a checkout of the repository "
               "(`visuotactile bench NAME` with an editable install, or `python -m benchmarks.NAME` from its root)")


def _benchmarks() -> ModuleType | None:
    """The checkout's ``benchmarks`` package (its root put on ``sys.path`` if needed), or None."""
    from perception.runtime import checkout_root

    root = checkout_root()
    if root is None or not (root / "benchmarks" / "__init__.py").is_file():
        return None
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module("benchmarks")


def available_benchmarks() -> list[str]:
    """Names of the modules in the checkout's ``benchmarks/`` (none outside a checkout)."""
    package = _benchmarks()
    if package is None:
        return []
    return sorted(m.name for m in pkgutil.iter_modules(package.__path__) if not m.name.startswith("_"))


def run(args: argparse.Namespace, rest: list[str]) -> int:
    names = available_benchmarks()
    if not names:
        print(f"visuotactile bench: error: {NOT_PRESENT}", file=sys.stderr)
        return 2
    usage = (f"usage: visuotactile bench NAME [options]; NAME is one of: {', '.join(names)}; "
             "`visuotactile bench NAME --help` lists its options")
    if args.name is None and {"-h", "--help"} & set(rest):
        print(usage)
        return 0
    if args.name is None:
        print(f"visuotactile bench: error: name a benchmark: one of {', '.join(names)}", file=sys.stderr)
        return 2
    if args.name not in names:
        print(f"visuotactile bench: error: unknown benchmark {args.name!r}; available: {', '.join(names)}",
              file=sys.stderr)
        return 2
    module = importlib.import_module(f"benchmarks.{args.name}")
    return int(module.main(rest) or 0)


def register(sub) -> None:
    # No help flag of its own: `bench NAME --help` reaches the benchmark's parser.
    bench = sub.add_parser(
        "bench", add_help=False, help="run a benchmark from the checkout's benchmarks/ (extra arguments, e.g. --json, "
                                      "are passed on)"
    )
    bench.add_argument("name", nargs="?", help="a benchmark of the checkout's benchmarks/ (no NAME: the list)")
    bench.set_defaults(func=run, passes_extra_args=True)
