"""The ``active`` part: next-touch policies compared on unseen objects in any pose.

Grouped k-fold by object over the unseen-objects store (the ``unseen`` part's objects, contours and folds; one
classifier per fold trained on every training sequence, both strategies: the ``unseen`` part's own fold models,
:func:`fold_models`). Each test object is turned by its
seeded random pose (:func:`fusion.experiments.data.any_pose`); its visual model is a noisy copy of that mesh
(vertices moved along their normals by N(0, ``noise_mm``) mm, seeded per object) or, with the camera in the loop, a
virtual OAK-D reconstruction (:func:`camera_models`). Every policy runs ``episodes`` episodes of ``max(ks)`` touches
per object (planning on the visual model, touching the true mesh; each episode seeded anew; the visual model's
saliency is computed once per object, as a robot looks once, and every saliency episode draws its own pair order
from it), so the decision after
K touches is an episode's first K touches fused by the log rule and an object's accuracy the share of its episodes
that decide right. Reported: accuracy against K with 95 %
bootstrap intervals over objects, paired differences (policy - random) bootstrapped over objects, the touches
needed to reach 90 %, the stopping rule at a posterior threshold (accuracy, touches used), and wall seconds per
decision step (planning, touching, classifying; the first step of the information policy includes simulating its
candidates).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.active import ActiveState, make_policy, noisy_copy, run_episode
from fusion.active.policies import (
    MAX_NOISE_MM,
    POLICIES,
    SMOOTH_ITERATIONS,
    InformationPolicy,
    SaliencyPolicy,
    smoothed,
    visual_belief,
)
from fusion.evaluate import accuracy
from fusion.experiments.models import fit_cached, pick
from perception import saliency as attention
from perception.atomic import atomic_path
from perception.errors import DatasetError, InvalidArgumentError, InvalidMeshError
from perception.geometry import ObjectModel
from perception.limits import check_count
from perception.validate import check_length
from tactile.explore import SequenceBatch
from tactile.sampling import STRATEGIES
from tactile.sensor import FSRSensor
from tactile.touching import touch

log = logging.getLogger(__name__)

BOOTSTRAP = 1000
#: Accuracy the "touches to reach" column asks for.
TARGET = 0.9
#: Posterior thresholds of the stopping-rule rows.
THRESHOLDS = (0.9, 0.99)
#: What the policies plan on (:func:`active_episodes`).
VISUALS = ("noisy", "camera")


def paired_over_objects(a: np.ndarray, b: np.ndarray, seed: int = 0) -> dict:
    """Mean of a - b (per-object scores, paired) with its 95 % percentile bootstrap interval over objects.

    Raises:
        InvalidArgumentError: unequal lengths or fewer than two objects.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or len(a) < 2:
        raise InvalidArgumentError(f"paired_over_objects: need two equal 1-D arrays of >= 2 objects, got {a.shape}, {b.shape}")
    diff = a - b
    rng = np.random.default_rng(seed)
    boot = diff[rng.integers(0, len(diff), size=(BOOTSTRAP, len(diff)))].mean(axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    return {"difference": float(diff.mean()), "low": float(low), "high": float(high), "n_objects": len(diff)}


#: Views of the virtual OAK-D orbit when the camera is in the loop (``visual="camera"``).
CAMERA_VIEWS = 4


def fold_order(names, specs) -> list[str]:
    """``names`` (sorted) taken class by class in turn: the first instance of every class, then the second..."""
    seen: dict[str, int] = {}
    rank = {}
    for name in names:
        label = specs[name].label
        rank[name] = seen.get(label, 0)
        seen[label] = rank[name] + 1
    return sorted(names, key=lambda n: (rank[n], specs[n].label, n))


def camera_models(captures: Path, spec, true, seed: int, views: int = CAMERA_VIEWS):
    """(visual, true) for the camera in the loop: ``true`` (the object in its pose) set upright on a table and
    captured by a virtual OAK-D from ``views`` orbit views (:func:`tactile.captures.virtual_capture`, stereo
    noise seeded by ``seed``); the visual model is the reconstruction, the true model the mesh as placed, both
    in the table's frame (mm, physical size). Cached in the folder ``captures`` (``captures/`` of the report
    folder; a capture takes about 3 s on 2 cores), named after the code that made it
    (:func:`tactile.dataset.generation_code_version`: capturing and reconstructing are ``tactile`` and
    ``perception`` code), so a capture of other code is made again."""
    import zlib

    from tactile.captures import virtual_capture
    from tactile.dataset import generation_code_version

    path = Path(captures) / (f"{spec.name.replace('/', '_')}-{zlib.crc32(spec.name.encode()):08x}"
                             f"-r{spec.rotation_seed}-s{seed}-v{views}-g{generation_code_version()}.npz")
    if path.is_file():
        with np.load(path) as saved:
            visual = ObjectModel(saved["visual_vertices"], saved["visual_triangles"], name=f"{true.name}@capture")
            placed = ObjectModel(saved["true_vertices"], true.triangles, name=true.name, label=true.label)
        if placed.n_vertices == true.n_vertices:
            return visual, placed
    capture = virtual_capture(true, views=views, seed=seed)
    visual = ObjectModel(capture.world.vertices, capture.world.triangles, name=f"{true.name}@capture")
    with atomic_path(path) as tmp:  # an interrupt leaves the old file or none, never half of one
        np.savez(tmp, visual_vertices=visual.vertices, visual_triangles=visual.triangles,
                 true_vertices=capture.truth.vertices)
    return visual, capture.truth


def capture_batch(ctx, names, specs, store, sensor, probes: int, contours: int, smooth_iterations: int,
                  touched: dict | None = None):
    """Touches on the camera's view of each training object (``names``, in their poses): ``contours`` blind contours
    of its virtual OAK-D reconstruction (:func:`camera_models`, the same capture a test object gets), smoothed as
    the information policy smooths what it plans on, labelled with the object's class. What a robot trained for
    the camera in the loop also learns from: how the objects it knows read when touched *on what the camera saw*.
    Objects whose capture finds nothing are left out (as at test time). ``touched``: name -> batch (None: no
    capture) of objects done already, filled here (an object trains in several folds; it is touched once)."""
    touched = {} if touched is None else touched
    for name in names:
        if name not in specs:
            raise DatasetError(f"active: training object {name!r} is not among the objects of this run")
        if name in touched:
            continue
        touched[name] = None
        try:
            seen, _ = camera_models(ctx.path("captures"), specs[name], specs[name].load(), ctx.seed)
        except InvalidMeshError as exc:
            log.warning("active: no capture of training object %s (%s)", name, exc)
            continue
        surface = smoothed(seen, smooth_iterations)
        # Named as the object itself: its touches and its capture's are one object to every grouped split (a
        # model search that trained on one and validated on the other would be fooled by the same object).
        labelled = ObjectModel(surface.vertices, surface.triangles, name=name, label=specs[name].label)
        sequences = touch(labelled, "blind", contours, sensor, probes, seed=ctx.seed)
        touched[name] = SequenceBatch.from_sequences(sequences, class_names=store.class_names,
                                                     sensor_spec=store.sensor_spec)
    batches = [touched[name] for name in names if touched[name] is not None]
    if not batches:
        raise DatasetError(f"active: none of the {len(names)} training objects' captures could be reconstructed; "
                           "train on the meshes alone (without train_on_captures)")
    return SequenceBatch.concatenate(batches)


@dataclass(frozen=True)
class EpisodeJob:
    """Every policy's episodes on one test object (:func:`active_episodes`), a job for
    :func:`fusion.experiments.parallel.run_jobs`: the fitted ``model`` (sent to the worker with the job), the
    object from its ``spec`` (in its pose); its visual model is a noisy copy seeded by ``noise_seed`` or its camera
    capture (cached in ``captures``). ``run()`` returns the object's record, or None when its capture finds no
    object."""

    spec: object
    model: object
    fold: int
    noise_seed: int
    visual: str
    noise_mm: float
    captures: str
    seed: int
    policies: tuple
    episodes: int
    max_touches: int
    candidates: int
    variants: int

    def run(self) -> dict | None:
        model, true = self.model, self.spec.load()
        name = self.spec.name
        if self.visual == "camera":
            try:
                seen, true = camera_models(Path(self.captures), self.spec, true, self.seed)
            except InvalidMeshError as exc:
                log.warning("active: %s left out, its capture failed (%s)", name, exc)
                return None
        else:
            seen = noisy_copy(true, self.noise_mm, seed=self.noise_seed)
        row = {"object": name, "label": true.label, "fold": self.fold, "policies": {}}
        options = {"information": {"candidates": self.candidates, "variants": self.variants}}
        if "saliency" in self.policies:  # the camera's view is looked at once, whatever the episodes then touch
            start = time.perf_counter()
            options["saliency"] = {"saliency": attention.saliency(seen, STRATEGIES[SaliencyPolicy.strategy],
                                                                  seed=self.seed)}
            row["saliency_s"] = time.perf_counter() - start
        for pname in self.policies:
            runs = []
            for e in range(self.episodes):  # episode e seeds the policy's draws and the sensor noise with seed + e
                policy = make_policy(pname, self.seed + e, **options.get(pname, {}))
                start = time.perf_counter()
                ep = run_episode(true, seen, model, policy, max_touches=self.max_touches, seed=self.seed + e)
                if e == 0 and isinstance(policy, InformationPolicy):  # what the camera's view alone would decide
                    outcomes = policy.simulated(ActiveState(seen, model))[1]
                    row["visual_decision"] = ep.classes[int(np.argmax(visual_belief([], outcomes)))]
                runs.append({
                    "decisions": ep.decisions(), "posteriors": ep.posteriors.round(6).tolist(),
                    "planning_s": ep.planning_s.tolist(), "touching_s": ep.touching_s.tolist(),
                    "classifying_s": ep.classifying_s.tolist(), "missed": int(ep.missed.sum()),
                    "classes": ep.classes, "seconds": time.perf_counter() - start})
            row["policies"][pname] = {**runs[0], **({"more_runs": runs[1:]} if len(runs) > 1 else {})}
        return row

    def cost(self) -> float:
        return 1.0

    def __str__(self) -> str:
        return f"active episodes on {self.spec.name}"


def _check_options(policies, candidates, variants, noise_mm, per_fold) -> tuple:
    """Refuse bad options of :func:`active_episodes` before its stores and fits (InvalidArgumentError);
    returns them as plain Python values (policies a tuple of str, candidates, variants, noise_mm a float,
    per_fold): numpy's integers and float32 would go to the JSON result as strings."""
    if isinstance(policies, str) or not isinstance(policies, (tuple, list)) or not policies:
        raise InvalidArgumentError(f"active: policies must be a non-empty list of names ({', '.join(POLICIES)}), "
                                   f"got {policies!r}")
    for name in policies:
        if name not in POLICIES:
            raise InvalidArgumentError(f"active: unknown touch policy {name!r}; choose from {', '.join(POLICIES)}")
    if len(set(policies)) != len(policies):
        raise InvalidArgumentError(f"active: a policy is named twice in {list(policies)}")
    # its own checks of the budget, whichever policies run: the result and the report name the budget
    InformationPolicy(0, candidates=candidates, variants=variants)
    noise_mm = check_length(noise_mm, "noise_mm", "active", maximum=MAX_NOISE_MM)
    if per_fold is not None and (isinstance(per_fold, bool) or not isinstance(per_fold, (int, np.integer))
                                 or per_fold < 1):
        raise InvalidArgumentError(f"active: per_fold must be an integer >= 1 or None (every test object), "
                                   f"got {per_fold!r}")
    return (tuple(str(name) for name in policies), int(candidates), int(variants), noise_mm,
            None if per_fold is None else int(per_fold))


def active_folds(ctx, objects) -> tuple:
    """The active part's plan: (its store, {object name: spec in its seeded pose}, per grouped fold (training rows, the
    base fit record of the models trained with captures (``train_on_captures``; the others are :func:`fold_models`),
    [(test object name, the noise seed of its visual model)] in :func:`fold_order`)). :func:`active_episodes` and
    ``benchmarks.active_replay`` both follow it and take the models of :func:`fold_models`, so a bank is built for the
    very objects, models and visual models of the part's episodes."""
    from fusion.experiments.data import any_pose
    from fusion.experiments.protocol import pooled_folds
    from tactile.dataset import object_specs

    sizes = ctx.sizes
    ds, record = ctx.store(objects, strategies=sizes.strategies, contours=sizes.unseen_contours)
    specs = {spec.name: spec for spec in object_specs(any_pose(objects, ctx.seed))}
    folds = []
    for i, (train, test) in enumerate(pooled_folds(ctx, ds, sizes.strategies, sizes.unseen_folds)):
        names = fold_order(sorted({ds.object_names[j] for j in np.unique(ds.object_ids[test])}), specs)
        folds.append((train, {"part": "active", "store": record, "train": [int(x) for x in train]},
                      [(name, ctx.seed + n + 1000 * i) for n, name in enumerate(names)]))
    return ds, specs, folds


def fold_models(ctx, objects, classifiers: dict) -> list[dict]:
    """Each grouped fold's fitted models, [{classifier name: model}] in fold order: the unseen-objects part's fold
    models (its training store, folds, training rows and classifiers), found in its cache or trained there side by
    side on the run's workers (and their upright test predictions made, which that part reads later). So a run with
    both parts trains each fold model once, and never on one core while the other waits.

    Raises:
        WorkerError, or what a fit raises (the first failure, once every fit has run).
    """
    from fusion.experiments.protocol import kfold_tasks, pose_stores

    sizes = ctx.sizes
    # the unseen part's upright stores: with more training contours (unseen_train_contours) the models train on
    # those, as the unseen part's do, and the folds deal the same objects
    stores = pose_stores(ctx, objects, "upright", sizes.strategies, sizes.unseen_contours, sizes.unseen_train_contours)
    tasks = kfold_tasks(ctx, "unseen", stores, tuple(sizes.strategies), classifiers, sizes.unseen_folds, "upright")
    ctx.run(list(tasks.values()))
    models: list[dict] = [{} for _ in range(sizes.unseen_folds)]
    for (_, name, i), task in tasks.items():
        if name not in models[i]:  # read; trained here only if the file went bad beside predictions still cached
            models[i][name] = fit_cached(task.factory, task.train, task.model_path(), task.record)[0]
    return models


def fold_model_path(ctx, fold: int, file: str) -> Path:
    """Where the active part keeps fold ``fold``'s (1-based) model ``file``."""
    return ctx.path("models", "active", f"fold{fold}", file)


def active_episodes(ctx, objects, *, classifier: str | None = None, policies=POLICIES,
                    max_touches: int = 8, noise_mm: float = 1.0, candidates: int = 24, variants: int = 2,
                    visual: str = "noisy", per_fold: int | None = None, train_on_captures: bool = False,
                    episodes: int = 1, progress: bool = False) -> dict:
    """Run every policy on every test object of the grouped folds; returns per-object records (JSON-able).

    ``visual``: what the policies plan on: ``"noisy"`` (the mesh in its pose with N(0, ``noise_mm``) mm along
    the normals) or ``"camera"`` (a virtual OAK-D capture's reconstruction, :func:`camera_models`; the true
    mesh is touched where it stands on the table). ``per_fold``: only the first N test objects of each fold, taken
    class by class in turn (a balanced subset; a camera capture takes about 3 s on 2 cores). An object whose
    capture cannot be reconstructed (no object found on the table) is left out and listed in
    ``capture_failures``. ``episodes``: episodes per object and policy, episode e seeding the policies' draws (the
    random planes, the information policy's candidates, the saliency pair order) and the sensor noise with seed + e;
    an object's accuracy is then its mean over them: a policy's expected accuracy on that object, which one draw
    estimates with a spread of several points on 100 objects (a lucky or unlucky set of random planes).
    """
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise InvalidArgumentError(f"active: episodes must be an integer >= 1, got {episodes!r}")
    if isinstance(max_touches, bool) or not isinstance(max_touches, (int, np.integer)) or max_touches < 1:
        raise InvalidArgumentError(f"active: max_touches must be an integer >= 1, got {max_touches!r}")
    check_count("touches", int(episodes) * int(max_touches),
                f"active: {episodes} episodes x {max_touches} touches per object and policy")
    policies, candidates, variants, noise_mm, per_fold = _check_options(policies, candidates, variants,
                                                                        noise_mm, per_fold)
    if visual not in VISUALS:
        raise InvalidArgumentError(f"active: visual must be one of {', '.join(VISUALS)}, got {visual!r}")
    if train_on_captures and visual != "camera":
        raise InvalidArgumentError("active: train_on_captures needs the camera in the loop (visual='camera')")

    sizes = ctx.sizes
    if classifier is None:  # the SVM when the run has one, else its first unseen-objects classifier
        classifier = "svm" if "svm" in ctx.classifiers else ctx.sizes.unseen_classifiers[0]
    factory = pick(ctx.classifiers, [classifier])[classifier]  # an unknown name: refused before the store
    ds, specs, folds = active_folds(ctx, objects)
    trained = None if train_on_captures else fold_models(ctx, objects, {classifier: factory})
    rows, failures, touched = [], [], {}
    for i, (train, fit_record, tests) in enumerate(folds):
        if trained is not None:
            model = trained[i][classifier]
        else:
            names = sorted({ds.object_names[j] for j in np.unique(ds.object_ids[train])})
            sensor, probes = FSRSensor.from_spec(ds.sensor_spec), ds.probes
            load = lambda t=train, n=names, s=sensor, p=probes: SequenceBatch.concatenate(
                [ds.load(t), capture_batch(ctx, n, specs, ds, s, p, sizes.unseen_contours, SMOOTH_ITERATIONS,
                                           touched)])
            # (the objects captured are the training objects, which "train" names already)
            fit_record = fit_record | {"captures": {"views": CAMERA_VIEWS, "contours": sizes.unseen_contours,
                                                    "smoothing": SMOOTH_ITERATIONS}}
            model, _fit_s = fit_cached(factory, load, fold_model_path(ctx, i + 1, f"{classifier}-captures.vtm"),
                                       fit_record)
        if per_fold is not None:
            tests = tests[:int(per_fold)]
        names = [name for name, _ in tests]
        jobs = [EpisodeJob(specs[name], model, i + 1, noise_seed, visual, noise_mm,
                           str(ctx.path("captures")), ctx.seed, tuple(policies), int(episodes), int(max_touches),
                           candidates, variants) for name, noise_seed in tests]
        # the objects side by side on the run's workers (each policy's draws are seeded by the object's visual
        # model and the step, so an object's episodes do not depend on which objects came before it)
        for name, row in zip(names, ctx.run_jobs(jobs, f"episodes, fold {i + 1}", "object") if jobs else []):
            if row is None:
                failures.append(name)
                continue
            rows.append(row)
            log.info("active fold %d: %s (%s) %s", i + 1, name, row["label"],
                     {p: r["decisions"][-1] for p, r in row["policies"].items()})
    return {"objects": rows, "classifier": classifier, "noise_mm": noise_mm, "candidates": candidates,
            "variants": variants, "max_touches": max_touches, "visual": visual, "capture_failures": failures,
            "train_on_captures": bool(train_on_captures), "episodes": int(episodes)}


def _runs(row: dict, policy: str) -> list[dict]:
    """The episodes of ``policy`` on one object (the first, then any more, :func:`active_episodes`' ``episodes``)."""
    first = row["policies"][policy]
    return [first, *first.get("more_runs", [])]


def _correct(rows, policy: str) -> np.ndarray:
    """(objects, K) the share of an object's episodes whose decision after K touches is right (0 or 1 for one)."""
    return np.array([np.mean([[d == r["label"] for d in run["decisions"]] for run in _runs(r, policy)], axis=0)
                     for r in rows], dtype=np.float64)


def summarize(result: dict, seed: int = 0) -> dict:
    """Accuracy against K (bootstrap over objects), paired differences against random, touches to reach
    :data:`TARGET`, stopping-rule rows and per-step timings of :func:`active_episodes`' result."""
    rows = result["objects"]
    if not rows:
        raise DatasetError("active: no test object was run (none asked for, or every capture failed): nothing to "
                           "summarize")
    policies = list(rows[0]["policies"])
    if len(rows) < 2 and "random" in policies and len(policies) > 1:
        raise DatasetError(f"active: {len(rows)} test object was run ({len(result.get('capture_failures', []))} "
                           "left out, their captures failed): the paired differences against random need at least 2")
    ks = range(1, result["max_touches"] + 1)
    groups = np.arange(len(rows))
    curve, differences, reach, stopping, timing, accs_by_policy = [], [], {}, [], [], {}
    random_right = _correct(rows, "random") if "random" in policies else None
    for p in policies:
        # Every episode is one decision, grouped by its object (the bootstrap resamples objects).
        runs = [(r["label"], g, run) for r, g in zip(rows, groups) for run in _runs(r, p)]
        labels = np.array([label for label, _, _ in runs], dtype=object)
        run_groups = np.array([g for _, g, _ in runs])
        right = random_right if p == "random" else _correct(rows, p)
        accs = []
        for k in ks:
            predicted = np.array([run["decisions"][k - 1] for _, _, run in runs], dtype=object)
            acc = accuracy(labels, predicted, groups=run_groups, n_boot=BOOTSTRAP, seed=seed).to_dict()
            curve.append({"policy": p, "k": k, "accuracy": acc})
            accs.append(acc["value"])
            if p != "random" and "random" in policies:
                differences.append({"policy": p, "k": k, **paired_over_objects(right[:, k - 1], random_right[:, k - 1],
                                                                               seed)})
        hit = [k for k, a in zip(ks, accs) if a >= TARGET]
        reach[p] = hit[0] if hit else None
        accs_by_policy[p] = accs
        for threshold in THRESHOLDS:
            used, good = [], []
            for label, _, run in runs:
                post = np.asarray(run["posteriors"])
                reached = np.flatnonzero(post.max(axis=1) >= threshold)
                k = int(reached[0]) + 1 if len(reached) else len(post)
                used.append(k)
                good.append(run["decisions"][k - 1] == label)
            stopping.append({"policy": p, "threshold": threshold, "accuracy": float(np.mean(good)),
                             "mean_touches": float(np.mean(used))})
        plan = np.array([run["planning_s"] for _, _, run in runs])
        touch_s = np.array([run["touching_s"] for _, _, run in runs])
        clf_s = np.array([run["classifying_s"] for _, _, run in runs])
        step = plan + touch_s + clf_s
        timing.append({"policy": p, "planning_first_s": float(np.median(plan[:, 0])),
                       "planning_later_s": float(np.median(plan[:, 1:])) if plan.shape[1] > 1 else 0.0,
                       "planning_mean_s": float(plan.mean()), "touching_s": float(np.median(touch_s)),
                       "classifying_s": float(np.median(clf_s)), "step_mean_s": float(step.mean()),
                       "episode_s": float(np.median(step.sum(axis=1)))})
    # Touches each policy needs to reach random's accuracy after the full budget.
    to_random = {}
    if "random" in accs_by_policy:
        goal = accs_by_policy["random"][-1]
        to_random = {p: next((k for k, a in zip(ks, accs) if a >= goal - 1e-12), None)
                     for p, accs in accs_by_policy.items()}
    looked = [r["saliency_s"] for r in rows if "saliency_s" in r]
    for t in timing:
        if t["policy"] == "saliency" and looked:  # once per object, before the episodes: not in their steps
            t["saliency_per_object_s"] = float(np.median(looked))
    visual_only = None
    if all("visual_decision" in r for r in rows):
        visual_only = float(np.mean([r["visual_decision"] == r["label"] for r in rows]))
    return {"curve": curve, "differences": differences, "touches_to_90": reach, "stopping": stopping,
            "timing": timing, "n_objects": len(rows), "classifier": result["classifier"],
            "noise_mm": result["noise_mm"], "candidates": result["candidates"], "variants": result["variants"],
            "visual": result.get("visual", "noisy"), "train_on_captures": result.get("train_on_captures", False),
            "episodes_per_object": result.get("episodes", 1),
            "touches_to_random_max": to_random,
            "visual_only_accuracy": visual_only}


def part_suffix(visual: str, train_on_captures: bool, classifier: str | None = None) -> str:
    """What tells a run's files apart: "" (noisy copies, the default classifier), "_camera", "_camera_captures"
    (trained on captures too), then "_<classifier>" when one is named."""
    return (("" if visual == "noisy" else f"_{visual}") + ("_captures" if train_on_captures else "")
            + (f"_{classifier}" if classifier else ""))


def active_part(ctx, objects, **options) -> dict:
    """The ``active`` part (cached in the report folder): :func:`summarize` of :func:`active_episodes`."""
    record = {"objects": [str(o) for o in objects], "sizes": ctx.sizes.to_dict(), "seed": ctx.seed,
              "options": {k: v for k, v in options.items() if k != "progress"}}
    if "saliency" in options.get("policies", POLICIES):  # until 2026-12-07 once per episode, with its seed
        record["saliency"] = "once per object"
    name = "active" + part_suffix(options.get("visual", "noisy"), options.get("train_on_captures", False),
                                  options.get("classifier"))
    result = ctx.cached_part(name, record, lambda: active_episodes(ctx, objects, **options))
    return {**summarize(result, ctx.seed), "episodes": f"parts/{name}.json"}


def render_markdown(summary: dict) -> str:
    """The part's section of the report."""
    seen = ("virtual OAK-D reconstruction" if summary.get("visual") == "camera"
            else f"mesh + {summary['noise_mm']} mm noise")
    if summary.get("train_on_captures"):
        seen += ", classifier also trained on touches of the training objects' reconstructions"
    lines = [(f"## Active touch (unseen objects, any pose, {summary['n_objects']} objects, "
             f"{summary['classifier']}, visual model: {seen}, "
             f"information: {summary['candidates']} candidates x {summary['variants']} variants"
             + (f", {summary['episodes_per_object']} episodes per object and policy"
                if summary.get("episodes_per_object", 1) > 1 else "")
             + ")"), "",
             "Accuracy after K touches (95 % bootstrap over objects):", "",
             "| policy | " + " | ".join(f"K={k}" for k in sorted({r['k'] for r in summary["curve"]})) + " | K for 90 % |",
             "|---|" + "---|" * (len({r['k'] for r in summary["curve"]}) + 1)]
    for p in dict.fromkeys(r["policy"] for r in summary["curve"]):
        cells = [f"{100 * r['accuracy']['value']:.1f} [{100 * r['accuracy']['low']:.0f}, {100 * r['accuracy']['high']:.0f}]"
                 for r in summary["curve"] if r["policy"] == p]
        lines.append(f"| {p} | " + " | ".join(cells) + f" | {summary['touches_to_90'][p] or '> max'} |")
    if summary.get("touches_to_random_max"):
        lines += ["", "Touches to reach random's accuracy after the whole budget: " + ", ".join(
            f"{p} {k or '> max'}" for p, k in summary["touches_to_random_max"].items()) + "."]
    if summary.get("visual_only_accuracy") is not None:
        lines += ["", (f"The visual model alone (every candidate's simulated touch pooled, no real touch): "
                       f"{100 * summary['visual_only_accuracy']:.1f} %.")]
    lines += ["", "Paired difference against random (points, 95 % bootstrap over objects):", "",
              "| policy | K | difference | interval |", "|---|---|---|---|"]
    lines += [f"| {d['policy']} | {d['k']} | {100 * d['difference']:+.1f} | [{100 * d['low']:+.1f}, {100 * d['high']:+.1f}] |"
              for d in summary["differences"]]
    lines += ["", "Stopping rule (stop when the fused posterior reaches the threshold, budget 8):", "",
              "| policy | threshold | accuracy | mean touches |", "|---|---|---|---|"]
    lines += [f"| {s['policy']} | {s['threshold']} | {100 * s['accuracy']:.1f} | {s['mean_touches']:.2f} |"
              for s in summary["stopping"]]
    lines += ["", "Wall seconds per decision step (medians; first planning step includes simulating the candidates):",
              "", "| policy | planning, first | planning, later | planning, mean | touching | classifying | step, mean |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {t['policy']} | {t['planning_first_s']:.3f} | {t['planning_later_s']:.4f} | {t['planning_mean_s']:.3f} | "
              f"{t['touching_s']:.3f} | {t['classifying_s']:.3f} | {t['step_mean_s']:.3f} |" for t in summary["timing"]]
    lines += [f"\nThe saliency policy's multiview saliency of the visual model, once per object before its episodes "
              f"(not in the steps above): {t['saliency_per_object_s']:.3f} s (median)."
              for t in summary["timing"] if "saliency_per_object_s" in t]
    return "\n".join(lines) + "\n"


__all__ = ["TARGET", "THRESHOLDS", "active_episodes", "active_part", "capture_batch", "paired_over_objects",
           "part_suffix", "render_markdown", "summarize"]


def main(argv=None) -> dict:
    """``python -m fusion.experiments.active --data FOLDER --out FOLDER [--quick] [--visual camera]``: the part on
    its own; writes ``results.json`` and ``report.md`` (``results_camera.json``, ``report_camera.md``) to ``--out``
    (stores, models, captures and episodes cached there)."""
    import json
    import re
    from pathlib import Path

    from fusion.cli import SEED_MAX, _Parser, check_common
    from fusion.commands.camera import SEED_MAX as CAMERA_SEED_MAX
    from fusion.experiments.config import FULL, QUICK
    from fusion.experiments.context import Context
    from fusion.experiments.data import folder_objects
    from fusion.experiments.models import default_classifiers
    from perception.atomic import write_text
    from perception.runtime import machine_line

    # one-line errors, as the visuotactile command line's (argparse's own print the whole usage first)
    parser = _Parser(prog="python -m fusion.experiments.active", description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--quick", action="store_true", help="QUICK sizes (4 objects per class, 16 contours)")
    parser.add_argument("--classifier", default=None, help="svm, knn or cnn (default: svm)")
    parser.add_argument("--seed", type=int, default=0,
                        help=f"0 to {SEED_MAX} (0 to {CAMERA_SEED_MAX} with --visual camera)")
    parser.add_argument("--max-touches", type=int, default=8)
    parser.add_argument("--noise-mm", type=float, default=1.0)
    parser.add_argument("--candidates", type=int, default=24)
    parser.add_argument("--variants", type=int, default=2)
    parser.add_argument("--policies", default="random,saliency,information",
                        help="comma-separated policies (random first: the others are paired against it)")
    parser.add_argument("--per-fold", type=int, default=None,
                        help="only the first N test objects of each fold, class by class in turn")
    parser.add_argument("--visual", choices=VISUALS, default="noisy",
                        help="plan on a noisy copy of the mesh or on a virtual OAK-D capture's reconstruction")
    parser.add_argument("--episodes", type=int, default=1,
                        help="episodes per object and policy, each seeded anew (accuracy = their mean per object)")
    parser.add_argument("--train-on-captures", action="store_true",
                        help="with --visual camera: the classifier also learns from touches on the training objects' "
                             "reconstructions")
    args = parser.parse_args(argv)
    # checked as the visuotactile command line checks it (32 bits; 31 where the camera's capture seeds Open3D)
    args.seed_max = CAMERA_SEED_MAX if args.visual == "camera" else SEED_MAX
    check_common(args)
    policies = tuple(p for p in args.policies.split(",") if p)
    try:  # the options' own checks, before the data is read, in one line naming the flag
        _check_options(policies, args.candidates, args.variants, args.noise_mm, args.per_fold)
    except InvalidArgumentError as exc:
        parser.error(re.sub(r"\b(noise_mm|per_fold)\b", lambda m: "--" + m.group(1).replace("_", "-"), str(exc)))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    sizes = QUICK if args.quick else FULL
    ctx = Context(Path(args.out), args.seed, sizes, default_classifiers(args.seed, sizes.epochs), progress=False)
    objects = folder_objects(args.data, None, sizes.unseen_per_class)
    start = time.perf_counter()
    summary = active_part(ctx, objects, classifier=args.classifier, max_touches=args.max_touches,
                          noise_mm=args.noise_mm, candidates=args.candidates, variants=args.variants,
                          policies=policies, visual=args.visual,
                          per_fold=args.per_fold, train_on_captures=args.train_on_captures,
                          episodes=args.episodes)
    summary |= {"command": "python -m fusion.experiments.active " + " ".join(argv if argv is not None else
                                                                            __import__("sys").argv[1:]),
                "machine": machine_line(), "seconds": round(time.perf_counter() - start, 1)}
    suffix = part_suffix(args.visual, args.train_on_captures, args.classifier)
    write_text(Path(args.out) / f"results{suffix}.json", json.dumps(summary, indent=2, default=str))
    write_text(Path(args.out) / f"report{suffix}.md", f"`{summary['command']}` ({summary['machine']}, "
               f"{summary['seconds']} s)\n\n" + render_markdown(summary))
    return summary


def cli(argv=None) -> int:
    """What ``python -m fusion.experiments.active`` runs: :func:`main`, refused input said in one line on stderr
    (as the visuotactile command line says it); returns the exit status (argparse exits 2 itself)."""
    import sys

    from perception.errors import VisuotactileError

    try:
        main(argv)
    except VisuotactileError as exc:
        print(f"python -m fusion.experiments.active: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    import sys
    from importlib import import_module

    # The package's copy of this module, not __main__: jobs built from its classes pickle by their package name,
    # so the run's worker processes can take them (jobs naming __main__ run one by one in this process).
    sys.exit(import_module("fusion.experiments.active").cli())
