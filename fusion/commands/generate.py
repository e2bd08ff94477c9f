"""``visuotactile generate``: explore a mesh collection or catalogue objects into a tactile dataset store.

    visuotactile generate (--data FOLDER [--classes ...] [--objects-per-class N] | --catalogue N)
        --out STORE [--captures N] [--strategies guided blind] [--contours 950] [--probes 25] [--workers N]
        [--executor local|ray] [--seed 0] [--strict] [--timeout S] [--json]

``--captures N`` adds N virtual depth-camera captures of every object (:mod:`tactile.captures`: the object set on a
table, seen by a virtual OAK-D from 4 views, reconstructed as ``visuotactile camera`` reconstructs): a classifier
trained on them meets reconstructions as it will on the robot. Splits by object keep each capture with its object.

Re-running the same command resumes (complete, intact objects are skipped; damaged ones are explored again);
other settings on an existing store are refused. Exit code 0 when every object is complete, 1 when some failed (they are listed and
recorded in the store), 2 on bad input or, with --strict, at the first failure.
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from fusion.commands import positive_int, print_json


def _objects(args: argparse.Namespace) -> list:
    """(class, seed) or (path, class) pairs from the arguments (:mod:`fusion.experiments.data`), and with
    ``--captures`` their captures' specs after them."""
    from fusion.experiments.data import catalogue_objects, folder_objects

    if args.catalogue is not None:
        from perception.shapes import CLASSES

        objects = catalogue_objects(args.classes or list(CLASSES), args.catalogue)
    else:
        objects = folder_objects(args.data, classes=args.classes, per_class=args.objects_per_class)
    if not args.captures:
        return objects
    from perception.limits import check_count
    from tactile.captures import training_specs

    # before a spec is built: 10**8 captures would fill the memory first
    check_count("objects", len(objects) * (1 + args.captures), f"--captures {args.captures}: the objects with their "
                                                                 "captures")

    return training_specs(objects, "both", captures_per_object=args.captures)


def _command(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (recorded in the store)."""
    words = ["visuotactile", "generate"]
    if args.catalogue is not None:
        words += ["--catalogue", str(args.catalogue)]
    else:
        words += ["--data", str(args.data)]
    if args.classes:
        words += ["--classes", *args.classes]
    if args.objects_per_class is not None:
        words += ["--objects-per-class", str(args.objects_per_class)]
    if args.captures:
        words += ["--captures", str(args.captures)]
    words += ["--out", str(args.out), "--strategies", *args.strategies, "--contours", str(args.contours),
              "--probes", str(args.probes), "--seed", str(args.seed)]
    return shlex.join(words)


def _store_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from perception.atomic import check_output_folder
    from tactile.dataset import generate, open_dataset

    objects = _objects(args)
    args.out = check_output_folder(args.out, "--out")
    report = generate(
        objects, args.out, strategies=tuple(args.strategies), contours_per_object=args.contours,
        probes=args.probes, seed=args.seed, workers=args.workers, executor=args.executor, strict=args.strict,
        object_timeout_s=args.timeout,
        command=_command(args),
    )
    dataset = open_dataset(report.path)
    size = _store_bytes(report.path)
    result = {
        **report.to_dict(),
        "complete_objects": len(dataset.object_names),
        "stored_sequences": len(dataset),
        "classes": list(dataset.class_names),
        "strategies": list(dataset.strategies),
        "store_bytes": size,
        "bytes_per_sequence": round(size / len(dataset), 1) if len(dataset) else None,
        "max_frame_error": dataset.max_frame_error,
        "failed_in_store": dataset.failed,
    }
    if args.json:
        print_json(result)
    else:
        print(f"store      {report.path}")
        print(f"objects    {len(dataset.object_names)}/{report.objects} complete "
              f"({report.completed} now, {report.skipped} already), {len(dataset.failed)} failed")
        for name, problem in report.repaired:
            print(f"repaired   {name} (was damaged: {problem})")
        print(f"sequences  {len(dataset)} stored, {report.sequences} written in {report.seconds:.1f} s "
              f"({report.sequences_per_s:.0f}/s)")
        print(f"classes    {len(dataset.class_names)}: {', '.join(dataset.class_names)}")
        print(f"strategies {', '.join(dataset.strategies)}; {dataset.probes} probes x "
              f"{dataset.grid[0]} x {dataset.grid[1]} taxels")
        print(f"size       {size / 1e6:.1f} MB, {result['bytes_per_sequence'] or 0:.0f} bytes/sequence, "
              f"frames within {dataset.max_frame_error:.2g} of the pressed readings")
        for name, reason in list(dataset.failed.items())[:10]:
            print(f"failed     {name}: {reason}")
        if len(dataset.failed) > 10:
            print(f"failed     ... and {len(dataset.failed) - 10} more (see {report.path / 'records'})")
    return 1 if dataset.failed else 0


def register(sub) -> None:
    p = sub.add_parser(
        "generate", help="explore objects into a tactile dataset store (zarr; resumable)",
        description=__doc__.split("\n\n")[0] + " Re-running resumes; exit 1 if some objects failed.",
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, help="class-per-folder mesh collection (<root>/<Class>/<file>)")
    source.add_argument("--catalogue", type=positive_int, metavar="N", help="N built-in objects per class (seeds 0..N-1)")
    p.add_argument("--classes", nargs="+", help="only these classes (default: all)")
    p.add_argument("--objects-per-class", type=positive_int, metavar="N", help="with --data: the first N files of each class")
    # A string, checked in run(): Path("") would already read as the current folder.
    p.add_argument("--out", required=True, help="the store folder (created, or resumed)")
    p.add_argument("--captures", type=positive_int, default=None, metavar="N",
                   help="also N virtual depth-camera captures of each object (reconstructions as the camera makes "
                        "them, about 5 s each), kept with their object in splits")
    p.add_argument("--strategies", nargs="+", default=["guided", "blind"],
                   help="sampling strategies: blind, guided, mesh, iss (default: guided blind)")
    p.add_argument("--contours", type=positive_int, default=950, help="contours per object and strategy (default: 950, the paper's)")
    p.add_argument("--probes", type=positive_int, default=25, help="probes per contour (default: 25)")
    p.add_argument("--workers", type=positive_int, default=None, help="parallel workers (default: the usable cores)")
    p.add_argument("--executor", default="local",
                   help="local processes or a Ray cluster (RAY_ADDRESS, else a local Ray instance)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--strict", action="store_true", help="stop at the first failed object")
    p.add_argument("--timeout", type=float, default=None, metavar="S",
                   help="give up on an object after S seconds (local executor)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.set_defaults(func=run, resumable=True)
