"""``visuotactile verify STORE``: check every complete object of a dataset store for damage.

Every chunk file of an object's rows must exist and pass its checksum, and each array's rows must match the
digest in the object's completion record (:func:`tactile.dataset.verify_store`). Exit code 0 when nothing is
damaged, 1 when some objects are (they are listed; re-running ``generate`` with the store's command explores
exactly them again), 2 when STORE is not a readable store.

``--rerun N`` also explores N of its objects again from the store's settings and compares the bytes
(:func:`tactile.dataset.rerun_objects`): rows edited or forged together with their checksums, or a store that this
version of the code would not make, are told apart from the real thing. Exit code 1 when one differs, or when
one could not be explored again (a loader object, a mesh not found: it is not verified).
"""

from __future__ import annotations

import argparse

from fusion.commands import positive_int, print_json
from perception.errors import InvalidArgumentError


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from tactile.dataset import verify_store

    if not args.rerun and (args.seed is not None or args.data is not None):  # before a long verification
        raise InvalidArgumentError("verify: --seed and --data choose and find the objects of --rerun; give --rerun N")
    report = verify_store(args.store)
    rerun = None
    if args.rerun:
        from tactile.dataset import rerun_objects

        rerun = rerun_objects(args.store, args.rerun, seed=args.seed or 0, data=args.data, progress=not args.json)
    ok = report.ok and (rerun is None or rerun.ok)
    if args.json:
        print_json(report.to_dict() | ({"rerun": rerun.to_dict(), "ok": ok} if rerun else {}))
    else:
        state = "intact" if report.ok else f"{len(report.damaged)} damaged"
        print(f"{report.path}: {report.checked} complete objects checked in {report.seconds:.1f} s, {state}; "
              f"{len(report.failed)} failed, {len(report.incomplete)} not yet explored")
        for name, problem in report.damaged.items():
            print(f"damaged  {name}: {problem}")
        if not report.ok:
            print("re-run generate with the store's settings to explore the damaged objects again")
        if rerun:
            print(f"explored again in {rerun.seconds:.1f} s: {len(rerun.same)} the same, {len(rerun.differ)} "
                  f"different, {len(rerun.skipped)} skipped")
            for name, arrays in rerun.differ.items():
                print(f"differs  {name}: {arrays}")
            for name, why in rerun.skipped.items():
                print(f"skipped  {name}: {why}")
    return 0 if ok else 1


def register(sub) -> None:
    p = sub.add_parser("verify", help="check a dataset store for missing or damaged chunks (checksums, digests)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("store", help="dataset store written by `visuotactile generate`")
    p.add_argument("--rerun", type=positive_int, metavar="N",
                   help="also explore N objects again from the store's settings and compare the bytes")
    p.add_argument("--seed", type=int, default=None, help="which objects --rerun draws (default 0)")
    p.add_argument("--data", metavar="FOLDER", help="mesh folder for --rerun, for a store made on another machine")
    p.add_argument("--json", action="store_true", help="print a JSON report on stdout")
    p.set_defaults(func=run)
