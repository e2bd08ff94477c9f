"""``visuotactile verify STORE``: check every complete object of a dataset store for damage.

Every chunk file of an object's rows must exist and pass its checksum, and each array's rows must match the
digest in the object's completion record (:func:`tactile.dataset.verify_store`). Exit code 0 when nothing is
damaged, 1 when some objects are (they are listed; re-running ``generate`` with the store's command explores
exactly them again), 2 when STORE is not a readable store.
"""

from __future__ import annotations

import argparse

from fusion.commands import print_json


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from tactile.dataset import verify_store

    report = verify_store(args.store)
    if args.json:
        print_json(report.to_dict())
    else:
        state = "intact" if report.ok else f"{len(report.damaged)} damaged"
        print(f"{report.path}: {report.checked} complete objects checked in {report.seconds:.1f} s, {state}; "
              f"{len(report.failed)} failed, {len(report.incomplete)} not yet explored")
        for name, problem in report.damaged.items():
            print(f"damaged  {name}: {problem}")
        if not report.ok:
            print("re-run generate with the store's settings to explore the damaged objects again")
    return 0 if report.ok else 1


def register(sub) -> None:
    p = sub.add_parser("verify", help="check a dataset store for missing or damaged chunks (checksums, digests)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("store", help="dataset store written by `visuotactile generate`")
    p.add_argument("--json", action="store_true", help="print a JSON report on stdout")
    p.set_defaults(func=run)
