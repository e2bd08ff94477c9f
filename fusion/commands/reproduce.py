"""``visuotactile reproduce --data FOLDER``: the paper's Table 1 and the experiments beyond it, as a report."""

from __future__ import annotations

import argparse
import os
import re
import reprlib
import sys
from pathlib import Path

from fusion.commands import positive_int

#: Instances per class of a ``catalogue:`` outlier item without a count.
CATALOGUE_OUTLIERS = 3


def outlier_objects(items) -> list[tuple]:
    """The outlier objects of ``--outliers``, in the order given: (mesh path, "outlier") for each mesh file, and for
    each mesh file directly in a folder (:func:`perception.loading.mesh_files`: sorted, hidden ones ignored);
    (class, seed) pairs of the built-in catalogue (:mod:`perception.shapes`) for an item
    ``catalogue:CLASS[,CLASS...][:N]`` (N instances per class, seeds 0..N-1; default :data:`CATALOGUE_OUTLIERS`;
    a file of that name is reached as ``./catalogue:...``).

    Raises:
        DatasetError: an empty item, a path that is neither a mesh file nor a folder holding one, or two items
            giving objects of one name (the store needs unique names).
        InvalidArgumentError: a ``catalogue:`` item naming no, an unknown or a repeated class, a count that is not
            a positive integer, more objects than the limit, or an item that is also a file or folder here.
    """
    from perception.errors import DatasetError
    from perception.limits import check_count
    from perception.loading import mesh_files
    from perception.meshio import MESH_SUFFIXES
    from tactile.dataset import object_specs

    objects = []
    for item in map(str, items):
        if item.startswith("catalogue:"):
            objects += _catalogue_item(item)
            continue
        if not item:
            raise DatasetError("--outliers: an empty item (a mesh file, a folder of them or "
                               "catalogue:CLASS[,CLASS...][:N])")
        given = Path(item)
        if os.path.isdir(item):  # os.path: False, not an OSError, for a name too long for the system
            found = mesh_files(given)
            if not found:
                raise DatasetError(f"--outliers {_short(item)}: the folder holds no mesh file "
                                   f"({', '.join(sorted(MESH_SUFFIXES))})")
            objects += [(str(p), "outlier") for p in found]
        elif os.path.isfile(item) and given.suffix.lower() in MESH_SUFFIXES:
            objects.append((str(given), "outlier"))
        else:
            raise DatasetError(f"--outliers {_short(item)}: not a mesh file ({', '.join(sorted(MESH_SUFFIXES))}), a "
                               "folder of them or catalogue:CLASS[,CLASS...][:N]")
    check_count("objects", len(objects), f"--outliers: {len(objects)} objects")
    try:  # one store holds them all, under unique names: say so now, not after the parts' data is made
        object_specs(objects)
    except DatasetError as err:
        raise DatasetError(f"--outliers: {_short(str(err), 300)}") from None
    return objects


def _short(text: str, width: int = 160) -> str:
    """``text`` cut in the middle to ``width`` characters for an error line (a path keeps its start and its file
    name)."""
    if len(text) <= width:
        return text
    head = (width - 3) // 2
    return text[:head] + "..." + text[len(text) - (width - 3 - head):]


def _catalogue_item(item: str) -> list[tuple[str, int]]:
    """The (class, seed) pairs of one ``catalogue:CLASS[,CLASS...][:N]`` item."""
    from fusion.experiments.data import catalogue_objects
    from perception.errors import InvalidArgumentError
    from perception.shapes import CLASSES

    shown = _short(item)
    if os.path.exists(item):  # os.path, unlike Path, answers False for a name too long for the system
        raise InvalidArgumentError(f"--outliers {shown}: is both a built-in catalogue item and a file or folder here; "
                                   f"write ./{shown} for the file")
    fields = item.split(":")
    if len(fields) not in (2, 3) or not fields[1]:
        raise InvalidArgumentError(f"--outliers {shown}: expected catalogue:CLASS[,CLASS...][:N] (classes: "
                                   f"{', '.join(CLASSES)})")
    count = CATALOGUE_OUTLIERS
    if len(fields) == 3:
        if not re.fullmatch(r"[0-9]+", fields[2]) or not fields[2].strip("0"):  # ASCII digits, not all zeros
            raise InvalidArgumentError(f"--outliers {shown}: the count N must be a positive integer, got "
                                       f"{reprlib.repr(fields[2])}")
        if len(fields[2].lstrip("0")) > 9:
            raise InvalidArgumentError(f"--outliers {shown}: the count N is too large (at most 999999999 a class)")
        count = int(fields[2])
    classes = fields[1].split(",")
    if len(set(classes)) != len(classes):
        raise InvalidArgumentError(f"--outliers {shown}: a class is named twice")
    try:
        return catalogue_objects(classes, count)
    except InvalidArgumentError as err:
        raise InvalidArgumentError(f"--outliers {shown}: {_short(str(err), 300)}") from None


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.commands import print_json
    from fusion.evaluate import markdown_table
    from fusion.experiments import reproduce
    from fusion.experiments.report import pct, table1
    from perception.atomic import check_output_folder
    from perception.errors import InvalidArgumentError

    out = args.out or ("out/reproduce-quick" if args.quick else "out/reproduce")
    check_output_folder(out, "--out")
    if args.classes is not None and len(set(args.classes)) < 2:
        from fusion.experiments.data import folder_objects

        folder_objects(args.data, classes=args.classes)  # a bad folder or an unknown class is named first
        raise InvalidArgumentError(f"--classes {' '.join(args.classes)}: recognition needs at least two classes")
    results = reproduce(args.data, out, classes=args.classes, objects_per_class=args.objects_per_class,
                        quick=args.quick, seed=args.seed, parts=args.parts, workers=args.workers,
                        command=" ".join(["visuotactile", *sys.argv[1:]]),
                        outliers=outlier_objects(args.outliers) if args.outliers else None)
    if args.json:
        print_json(results)
        return 0
    if "paper" in results:
        print("Paper protocol (Table 1), test accuracy with 95 % interval:")
        print(markdown_table(table1(results["paper"]["rows"])))
    if "unseen" in results:
        print("\nUnseen objects (one touch):")
        print(markdown_table(table1(results["unseen"]["rows"])))
    if "touches" in results:
        rows = [r for r in results["touches"]["rows"] if r["rule"] == "log"]
        for setting in dict.fromkeys(r["setting"] for r in rows):
            k = max(r["k"] for r in rows if r["setting"] == setting)
            print(f"\n{setting.replace('_', ' ')}, K = {k} touches (sum of log probabilities):")
            for r in rows:
                if r["setting"] == setting and r["k"] == k:
                    print(f"  {r['classifier']:<28} {r['strategy']:<7} {pct(r['accuracy'])}")
    if "runtime" in results:
        points = results["runtime"]["points"]
        for name, i in results["runtime"]["named"].items():
            print(f"operating point {name}: {points[i]['label']}, error {100 * points[i]['error']:.1f} %, "
                  f"{points[i]['seconds']:.4f} s per decision")
    print(f"\nReport: {out}/report.md")
    return 0


#: fusion.experiments.PARTS, spelled out so that the command line starts without the experiment modules.
PARTS = ("paper", "unseen", "touches", "noise", "attention", "runtime", "calibration", "openset", "active")
#: fusion.experiments.reproduce.DEFAULT_PARTS (calibration, open set and active touch are asked for by name).
DEFAULT_PARTS = PARTS[:6]


def register(sub) -> None:
    parser = sub.add_parser(
        "reproduce", help="reproduce the paper's Table 1 on a mesh set and go beyond it (report folder)",
        description="Paper protocol (80/20 by sequence, guided and blind, CNN fusion and each modality, SVM, "
                    "kNN) next to the paper's Table 1; unseen objects, K touches, noise, attention models and "
                    "error vs run time. Stores and models are cached in the report folder: re-running resumes.")
    parser.add_argument("--data", required=True, help="class-per-folder mesh set (<root>/<Class>/<mesh>)")
    parser.add_argument("--classes", nargs="+", help="classes to use (default: the first 8 for the paper "
                                                      "protocol, all for unseen objects)")
    parser.add_argument("--objects-per-class", type=positive_int, default=None,
                        help="instances per class of the paper protocol (default 3)")
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke run: about 5 minutes on 2 cores)")
    parser.add_argument("--out", help="report folder (default out/reproduce, or out/reproduce-quick)")
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(DEFAULT_PARTS),
                        help=f"parts to run (default: {', '.join(DEFAULT_PARTS)})")
    parser.add_argument("--workers", type=positive_int, default=None,
                        help="worker processes of data generation and of model fits (default: the cores; any count "
                             "gives the same stores and CNN models: each CNN trains on one thread)")
    parser.add_argument("--outliers", nargs="+", metavar="PATH", default=None,
                        help="objects of no class in --data: mesh files, folders of them, or built-in shapes "
                             f"(catalogue:CLASS[,CLASS...][:N], N per class, default {CATALOGUE_OUTLIERS}); the "
                             "calibration and openset parts' CNNs also learn to doubt their touches (outlier "
                             "exposure). An instance of a class in --data (a mug where Cup is one) teaches them to "
                             "doubt that class")
    parser.add_argument("--seed", type=int, default=0, help="seed of data, splits, models and bootstraps")
    parser.add_argument("--json", action="store_true", help="print results.json on stdout")
    parser.set_defaults(func=run, resumable=True)
