"""Next-touch criteria screened offline on the active part's unseen objects (:mod:`fusion.active.replay`).

For every test object of the active part's grouped folds (each in its seeded random pose, its visual model the mesh
plus ``--noise-mm`` of noise, 1 mm by default, as ``python -m fusion.experiments.active`` makes them) and every policy
seed, one candidate bank:
the information policy's 24 candidates simulated on the visual model and touched on the true mesh, read by each
classifier's fold model. Then each (planner, decider) pair replays the information rule (the planner's simulated
outcomes and readings choose, the decider's readings decide), and each decider reads the candidates in a seeded
random order as a reference. With planner = decider the replay is the information policy's episode to the bit, so
the row "cnn -> cnn" equals the information row of ``python -m fusion.experiments.active --classifier cnn`` run with
the default seed 0 into the same folder (policy seeds 0..4 are its episodes 0..4), and the other rows are what a
changed planner would give, without touching anything again. The row "hindsight -> d" is no policy: it reads every
candidate's real reading and touches first those that most confirm what all of them pooled say (what classifier d
would decide with every candidate touched, reached as early as a choice can; :func:`fusion.active.replay.hindsight`).

Accuracy after K touches is the mean over an object's seeds, then over objects; differences are paired over
objects (95 % bootstrap). The fold models are those of the active part's run in ``--out`` (fitted there if absent).

    .venv/bin/python -m benchmarks.active_replay --data ../shared/data/shrec07 --out out/active \\
        --classifiers cnn,svm --seeds 0,1,2,3,4 [--json]
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks._common import DATA, machine

#: Touch budget of every replay.
BUDGET = 8


@dataclass(frozen=True)
class BankJob:
    """The banks of one object, one per policy seed (a job for the run's workers)."""

    spec: object
    models: dict
    noise_seed: int
    seeds: tuple
    noise_mm: float = 1.0

    def run(self) -> list:
        from fusion.active import InformationPolicy, noisy_copy
        from fusion.active.replay import build_bank

        true = self.spec.load()
        visual = noisy_copy(true, self.noise_mm, seed=self.noise_seed)  # as the active part's EpisodeJob makes it
        return [build_bank(true, visual, self.models, InformationPolicy(seed)) for seed in self.seeds]

    def cost(self) -> float:
        return 1.0

    def __str__(self) -> str:
        return f"banking {self.spec.name}"


def banks(data: Path, out: Path, classifiers: list[str], seeds: tuple, quick: bool, noise_mm: float = 1.0) -> list[dict]:
    """[{"object", "label", "banks"}] over the active part's test objects, fold by fold.

    Raises:
        InvalidArgumentError: fewer than two test objects (the differences are paired over objects), before any bank
            is made or model fitted.
    """
    # the job class by its module's name: run as ``python -m``, this module is __main__, which workers cannot import
    from benchmarks.active_replay import BankJob as job
    from fusion.experiments.active import active_folds, fold_models
    from fusion.experiments.config import FULL, QUICK
    from fusion.experiments.context import Context
    from fusion.experiments.data import folder_objects
    from fusion.experiments.models import default_classifiers, pick
    from perception.errors import InvalidArgumentError

    sizes = QUICK if quick else FULL
    ctx = Context(out, 0, sizes, default_classifiers(0, sizes.epochs), progress=True)
    objects = folder_objects(data, None, sizes.unseen_per_class)
    _, specs, folds = active_folds(ctx, objects)
    n_objects = sum(len(tests) for _, _, tests in folds)
    if n_objects < 2:
        raise InvalidArgumentError(f"{data}: {n_objects} test object(s); the replay's differences are paired over "
                                   "objects and need at least two")
    rows = []
    trained = fold_models(ctx, objects, pick(ctx.classifiers, classifiers))
    for i, ((_, _, tests), models) in enumerate(zip(folds, trained, strict=True)):
        jobs = [job(specs[name], models, noise_seed, seeds, noise_mm) for name, noise_seed in tests]
        for (name, _), made in zip(tests, ctx.run_jobs(jobs, f"banks, fold {i + 1}", "object"), strict=True):
            rows.append({"object": name, "label": specs[name].label, "banks": made, "seeds": list(seeds)})
    return rows


def _random_order(seed: int):
    """Candidates in a seeded random order (a reference: random planes drawn as the candidates are)."""
    def scores(view):
        order = np.random.default_rng(seed).permutation(len(view.touched))
        return -np.argsort(order).astype(np.float64)  # the earliest in the order scores highest
    return scores


def right(rows: list[dict], criterion_of, decide: str) -> np.ndarray:
    """(objects, BUDGET) the share of an object's seeds whose decision after K touches is right; ``criterion_of(seed)``
    is a criterion, or None for the hindsight reference (:func:`fusion.active.replay.hindsight`). The seed is the
    policy seed of the bank (a row's ``"seeds"``; without them, the bank's position), so the random order of policy
    seed s is the same whatever other seeds a run holds."""
    from fusion.active.replay import hindsight, replay

    out = []
    for row in rows:
        per_seed = []
        seeds = row.get("seeds", range(len(row["banks"])))
        for seed, bank in zip(seeds, row["banks"], strict=True):
            criterion = criterion_of(seed)
            _, posteriors = (hindsight(bank, decide, BUDGET) if criterion is None
                             else replay(bank, criterion, decide, BUDGET))
            per_seed.append([bank.classes[int(i)] == row["label"] for i in posteriors.argmax(axis=1)])
        out.append(np.mean(per_seed, axis=0))
    return np.asarray(out, dtype=np.float64)


def screen(rows: list[dict], classifiers: list[str]) -> dict:
    from fusion.active.replay import information_criterion
    from fusion.experiments.active import paired_over_objects

    table, differences = [], []
    for decide in classifiers:
        reference = right(rows, lambda s: _random_order(1000 + s), decide)
        own = right(rows, lambda s, d=decide: information_criterion(d), decide)
        table.append({"planner": "random order", "decider": decide, "accuracy": reference.mean(axis=0).tolist()})
        pooled = right(rows, lambda s: None, decide)
        table.append({"planner": "hindsight", "decider": decide, "accuracy": pooled.mean(axis=0).tolist()})
        for k in (1, 2, 4, 8):
            differences.append({"planner": "hindsight", "decider": decide, "k": k,
                                "vs_random_order": paired_over_objects(pooled[:, k - 1], reference[:, k - 1]),
                                "vs_own_planner": paired_over_objects(pooled[:, k - 1], own[:, k - 1])})
        for planner in classifiers:
            acc = own if planner == decide else right(rows, lambda s, p=planner: information_criterion(p), decide)
            table.append({"planner": planner, "decider": decide, "accuracy": acc.mean(axis=0).tolist()})
            for k in (1, 2, 4, 8):
                differences.append({"planner": planner, "decider": decide, "k": k,
                                    "vs_random_order": paired_over_objects(acc[:, k - 1], reference[:, k - 1]),
                                    "vs_own_planner": paired_over_objects(acc[:, k - 1], own[:, k - 1])})
    return {"objects": len(rows), "table": table, "differences": differences}


def _print(result: dict) -> None:
    print(f"{result['objects']} unseen objects in any pose, seeds {result['seeds']}, classifiers "
          f"{', '.join(result['classifiers'])}")
    print("planner -> decider         " + " ".join(f"K={k:<4d}" for k in range(1, BUDGET + 1)))
    for row in result["table"]:
        print(f"{row['planner'] + ' -> ' + row['decider']:26s} " + " ".join(f"{100 * a:6.1f}" for a in row["accuracy"]))
    print("\npaired differences, points [95 % bootstrap over objects]")
    for d in result["differences"]:
        a, b = d["vs_random_order"], d["vs_own_planner"]
        print(f"{d['planner']} -> {d['decider']} K={d['k']}: vs random order {100 * a['difference']:+.1f} "
              f"[{100 * a['low']:+.1f}, {100 * a['high']:+.1f}], vs {d['decider']} planning "
              f"{100 * b['difference']:+.1f} [{100 * b['low']:+.1f}, {100 * b['high']:+.1f}]")


def main(argv=None) -> dict:
    """The command line; a project error (a bad data folder, a damaged store or model) ends it with one line on
    stderr and exit status 2, as ``visuotactile`` commands end."""
    from fusion.active.policies import MAX_NOISE_MM
    from fusion.cli import SEED_MAX, _Parser
    from fusion.experiments.models import default_classifiers, pick
    from perception.errors import InvalidArgumentError, VisuotactileError
    from perception.validate import check_length

    parser = _Parser(prog="python -m benchmarks.active_replay", description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA / "shrec07")
    parser.add_argument("--out", type=Path, required=True, help="the active part's output folder (its store and fold models; fitted there if absent)")
    parser.add_argument("--classifiers", default="cnn,svm")
    parser.add_argument("--seeds", default="0,1,2,3,4", help="policy seeds (the active part's episodes 0..4)")
    parser.add_argument("--noise-mm", type=float, default=1.0,
                        help="the visual model's noise, mm (the active part's --noise-mm)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    classifiers = [c for c in args.classifiers.split(",") if c]
    try:
        seeds = tuple(int(s) for s in args.seeds.split(",") if s)
    except ValueError:
        parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
    if not classifiers or not seeds:
        parser.error("give at least one classifier and one seed")
    if any(not 0 <= s <= SEED_MAX for s in seeds):
        parser.error(f"--seeds must be integers from 0 to {SEED_MAX}, got {args.seeds!r}")
    try:  # before the data is read and the models fitted
        pick(default_classifiers(0), classifiers)
    except InvalidArgumentError as exc:
        parser.error(f"--classifiers: {exc}")
    try:
        noise_mm = check_length(args.noise_mm, "--noise-mm", "active_replay", maximum=MAX_NOISE_MM)
    except InvalidArgumentError as exc:
        parser.error(str(exc))
    if not args.data.is_dir():
        parser.error(f"--data {args.data} is not a folder")
    try:
        rows = banks(args.data, args.out, classifiers, seeds, args.quick, noise_mm)
    except VisuotactileError as exc:
        print(f"python -m benchmarks.active_replay: error: {exc}", file=sys.stderr)
        sys.exit(2)
    result = {"machine": machine(), "seeds": list(seeds), "classifiers": classifiers, "noise_mm": noise_mm,
              **screen(rows, classifiers)}
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        print()
    else:
        _print(result)
    return result


if __name__ == "__main__":
    main()
