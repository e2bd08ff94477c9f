"""``visuotactile evaluate``: a saved model on a dataset store, by sequence or with K touches per decision."""

from __future__ import annotations

import argparse
from pathlib import Path

from fusion.commands import positive_int, print_json

#: Figure formats --figure takes (by suffix).
FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def check_evaluate_args(args: argparse.Namespace) -> None:
    """``--touches`` a count within its limit, ``--figure`` a writable PNG/PDF/SVG file: checked before any work.

    Raises:
        InvalidArgumentError: naming the option, the value and the limit or the fix.
    """
    from perception.errors import InvalidArgumentError
    from perception.limits import check_count

    if args.touches < 1:
        raise InvalidArgumentError(f"--touches must be at least 1 (sequences per decision), got {args.touches}")
    check_count("touches", args.touches, "--touches")
    if args.figure is not None:
        check_figure(args.figure)


def check_figure(path, what: str = "--figure") -> None:
    """A figure file to write: a writable place (:func:`perception.atomic.check_output_file`) and a format
    matplotlib writes (:data:`FIGURE_SUFFIXES`), checked before any work (evaluate, recognize).

    Raises:
        InvalidArgumentError: naming the option, the path and the fix.
    """
    from perception.atomic import check_output_file
    from perception.errors import InvalidArgumentError

    check_output_file(path, what)
    if Path(path).suffix.lower() not in FIGURE_SUFFIXES:
        raise InvalidArgumentError(f"{what} {str(path)!r}: give a file ending in {', '.join(FIGURE_SUFFIXES)} "
                                   "(the figure's format)")


def run(args: argparse.Namespace, rest: list[str]) -> int:
    from fusion.base import load_model
    from fusion.evaluate import confusion, plot_confusion
    from fusion.training import evaluate_on_store

    check_evaluate_args(args)
    model = load_model(args.model, trust_pickle=args.trust_pickle)
    found = evaluate_on_store(model, args.store, touches=args.touches, rule=args.rule, strategy=args.strategy,
                              seed=args.seed)
    truth, predicted, classes = found.pop("truth"), found.pop("predicted"), found.pop("classes")
    acc, by_object = found.pop("interval"), found.pop("object_interval")
    result = {"model": str(args.model), "store": str(args.store), **found}
    if args.figure:
        plot_confusion(confusion(truth, predicted, classes), classes, args.figure,
                       title=f"{Path(args.model).name}, K = {args.touches}: {acc.percent()}")
        result["figure"] = str(args.figure)
    if args.json:
        print_json(result)
    else:
        print(f"{args.model} on {args.store} ({result['subset']}), K = {args.touches} touches ({args.rule} rule): "
              f"{acc.percent()} over {len(predicted)} decisions (interval resampling objects: "
              f"[{100 * by_object.low:.1f}, {100 * by_object.high:.1f}])")
        for name, value in result["per_class"].items():
            print(f"  {name:>14s}: " + ("-" if value is None else f"{100 * value:.1f} %"))
    return 0


def register(sub) -> None:
    from fusion.decide import RULES

    p = sub.add_parser("evaluate", help="evaluate a saved model on a dataset store")
    p.add_argument("--model", required=True, help="model file written by `visuotactile train` or the demo")
    p.add_argument("--store", required=True, help="dataset store")
    p.add_argument("--trust-pickle", action="store_true",
                   help="also load an old pickled model (runs code from the file: only for files you made)")
    p.add_argument("--touches", type=positive_int, default=1, help="sequences of the same object per decision (default: 1)")
    p.add_argument("--rule", choices=RULES, default="log", help="multi-touch fusion rule (default: log)")
    p.add_argument("--strategy", default=None, help="only this strategy's sequences (other stores)")
    p.add_argument("--figure", default=None, help="write a confusion-matrix PNG here")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print a JSON result on stdout")
    p.set_defaults(func=run)
