"""The active-touch experiment's scoring: paired differences over objects, accuracy against K, touches to reach
90 % and the stopping rule, on hand-made episodes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.experiments.active import paired_over_objects, render_markdown, summarize
from perception.errors import InvalidArgumentError


def _policy(decisions, top):
    return {"decisions": decisions, "posteriors": [[p, 1 - p] for p in top], "planning_s": [0.2, 0.01],
            "touching_s": [0.05, 0.05], "classifying_s": [0.01, 0.01], "missed": 0, "classes": ["a", "b"]}


def episodes():
    # 10 objects of class "a": random is right after 2 touches on 5 of them, information on all 10 (9 after 1).
    rows = []
    for i in range(10):
        rows.append({"object": f"o{i}", "label": "a", "fold": 1, "policies": {
            "random": _policy(["b", "a" if i < 5 else "b"], [0.6, 0.8]),
            "information": _policy(["a" if i else "b", "a"], [0.95 if i else 0.6, 0.995])}})
    return {"objects": rows, "classifier": "svm", "noise_mm": 1.0, "candidates": 4, "variants": 1, "max_touches": 2}


def test_paired_over_objects():
    a, b = np.array([1.0, 1.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0, 0.0])
    result = paired_over_objects(a, b)
    assert result["difference"] == pytest.approx(0.5) and result["n_objects"] == 4
    assert 0.0 <= result["low"] <= 0.5 <= result["high"] <= 1.0
    same = paired_over_objects(a, a)
    assert same["low"] == same["high"] == same["difference"] == 0.0
    with pytest.raises(InvalidArgumentError):
        paired_over_objects(a, b[:3])


def test_summary_known_answers():
    summary = summarize(episodes())
    acc = {(r["policy"], r["k"]): r["accuracy"]["value"] for r in summary["curve"]}
    assert acc == {("random", 1): 0.0, ("random", 2): 0.5, ("information", 1): 0.9, ("information", 2): 1.0}
    assert summary["touches_to_90"] == {"random": None, "information": 1}
    diff = {d["k"]: d for d in summary["differences"]}
    assert diff[1]["difference"] == pytest.approx(0.9) and diff[2]["difference"] == pytest.approx(0.5)
    assert diff[2]["low"] > 0
    stop = {(s["policy"], s["threshold"]): s for s in summary["stopping"]}
    # Threshold 0.9: information stops after 1 touch on 9 objects (right), after 2 on one (right).
    assert stop[("information", 0.9)]["mean_touches"] == pytest.approx(1.1)
    assert stop[("information", 0.9)]["accuracy"] == 1.0
    assert stop[("random", 0.9)]["mean_touches"] == 2.0 and stop[("random", 0.9)]["accuracy"] == 0.5
    timing = {t["policy"]: t for t in summary["timing"]}
    assert timing["random"]["planning_first_s"] == pytest.approx(0.2)
    assert timing["random"]["step_mean_s"] == pytest.approx((0.26 + 0.07) / 2)
    assert "| information | 1 | +90.0 |" in render_markdown(summary)


def test_reproduce_part_options():
    """The ``active`` reproduce part: its sizes are active_part's keywords, quick is smaller, the report renders it."""
    import inspect

    from fusion.experiments.active import active_episodes
    from fusion.experiments.config import FULL, QUICK
    from fusion.experiments.reproduce import DEFAULT_PARTS, PARTS

    assert "active" in PARTS and "active" not in DEFAULT_PARTS
    keywords = set(inspect.signature(active_episodes).parameters)
    assert set(FULL.active_options()) <= keywords
    assert QUICK.active_options()["candidates"] < FULL.active_options()["candidates"]
    from fusion.experiments.report import render

    text = render({"command": "c", "data": "d", "date": "t", "machine": "m", "seed": 0, "bootstrap": "b", "sizes": {},
                   "active": summarize(episodes())})
    assert "## Active touch" in text and "| information | 1 | +90.0 |" in text


@pytest.mark.slow
def test_reproduce_runs_the_active_part(tmp_path):
    """End to end through ``reproduce(parts=("active",))`` on tiny sizes with a stand-in classifier."""
    from fusion.experiments.reproduce import reproduce
    from tests.fusion.test_experiments import STANDINS, TINY, mesh_folder

    sizes = TINY.with_(active_policies=("random", "information"), active_touches=2, active_candidates=3,
                       active_variants=1)
    results = reproduce(mesh_folder(tmp_path / "meshes"), tmp_path / "report", sizes=sizes, classifiers=STANDINS,
                        parts=("active",), workers=1, progress=False)
    summary = results["active"]
    assert summary["classifier"] == "nm" and summary["n_objects"] >= 6
    assert {(r["policy"], r["k"]) for r in summary["curve"]} == {(p, k) for p in ("random", "information")
                                                                   for k in (1, 2)}
    assert "## Active touch" in (tmp_path / "report" / "report.md").read_text()


def test_capture_batch_touches_what_the_camera_saw(tmp_path, monkeypatch):
    """Training touches for the camera in the loop lie on each training object's reconstruction (smoothed as the
    planner smooths), not on its mesh; they carry the object's class; an object the camera cannot see is left out."""
    from types import SimpleNamespace

    from fusion.active.policies import smoothed
    from fusion.experiments import active
    from fusion.experiments.config import QUICK
    from fusion.experiments.context import Context
    from perception.errors import InvalidMeshError
    from tactile.dataset import ObjectSpec
    from tactile.sensor import FSRSensor

    ctx = Context(tmp_path, 0, QUICK, {}, progress=False)
    specs = {name: ObjectSpec(name, label, catalogue=(label, 0)) for name, label in
             (("mug/0", "mug"), ("box/0", "box"), ("can/0", "can"))}
    sensor = FSRSensor(rows=8, cols=8)
    store = SimpleNamespace(class_names=("box", "can", "mug"), sensor_spec=sensor.spec())
    real = active.camera_models

    def camera(captures, spec, true, seed):
        if spec.name == "can/0":
            raise InvalidMeshError("can/0: no object on the table")
        return real(captures, spec, true, seed)

    monkeypatch.setattr(active, "camera_models", camera)
    batch = active.capture_batch(ctx, ["mug/0", "box/0", "can/0"], specs, store, sensor, 8, 3, 2)
    assert len(batch) == 6 and batch.object_names == ("mug/0", "box/0")  # named as their objects
    assert [batch.class_names[k] for k in batch.labels] == ["mug"] * 3 + ["box"] * 3
    for k, name in enumerate(("mug/0", "box/0")):
        seen, true = real(ctx.path("captures"), specs[name], specs[name].load(), 0)  # cached: the same capture
        rows = batch.object_ids == k
        points = batch.positions[rows].reshape(-1, 3).astype(np.float64)  # the table's frame, mm
        surface = smoothed(seen, 2)
        on_seen = surface.scene.compute_distance(surface.to_scene(points).astype(np.float32)).numpy()
        on_true = true.scene.compute_distance(true.to_scene(points).astype(np.float32)).numpy()
        assert on_seen.max() < 1e-3  # probes sit on the surface the camera saw
        assert on_true.max() > 0.1  # ... which is not the object's own surface


def test_summary_averages_the_episodes_of_each_object():
    """With several episodes per object, an object's accuracy is the share of its episodes that are right, the
    paired difference pairs those shares, and the stopping rule counts every episode."""
    result = episodes()
    for i, row in enumerate(result["objects"]):
        # A second random episode per object: right after 2 touches on o5..o9 instead of o0..o4, and after 1 on o0.
        row["policies"]["random"]["more_runs"] = [_policy(["a" if i == 0 else "b", "a" if i >= 5 else "b"],
                                                          [0.95 if i == 0 else 0.6, 0.8])]
    result["episodes"] = 2
    summary = summarize(result)
    acc = {(r["policy"], r["k"]): r["accuracy"] for r in summary["curve"]}
    assert acc[("random", 1)]["value"] == pytest.approx(0.05) and acc[("random", 2)]["value"] == pytest.approx(0.5)
    assert acc[("random", 2)]["n"] == 20  # every episode is one decision ...
    # ... but the interval resamples objects: each object's two episodes give 1/2 at K = 2, so it cannot move.
    assert acc[("random", 2)]["low"] == acc[("random", 2)]["high"] == pytest.approx(0.5)
    diff = {d["k"]: d for d in summary["differences"]}
    assert diff[1]["difference"] == pytest.approx(0.9 - 0.05) and diff[2]["difference"] == pytest.approx(0.5)
    stop = {(s["policy"], s["threshold"]): s for s in summary["stopping"]}
    # Threshold 0.9: o0's second random episode stops after 1 touch (right); the other 19 episodes use both.
    assert stop[("random", 0.9)]["mean_touches"] == pytest.approx(39 / 20)
    assert stop[("random", 0.9)]["accuracy"] == pytest.approx(11 / 20)
    assert summary["episodes_per_object"] == 2 and "2 episodes per object" in render_markdown(summary)
    # active_part adds the path of the episodes file under "episodes": the report still renders.
    assert "2 episodes per object" in render_markdown({**summary, "episodes": "parts/active.json"})


def test_part_names_tell_runs_apart():
    from fusion.experiments.active import part_suffix

    names = {part_suffix(v, c, k) for v in ("noisy", "camera") for c in (False, True) for k in (None, "cnn", "knn")
             if not (c and v == "noisy")}
    assert len(names) == 9  # every run its own files: no run's cached episodes overwrite another's
    assert part_suffix("noisy", False) == "" and part_suffix("camera", True, "cnn") == "_camera_captures_cnn"


# ------------------------------------------------------------------ episodes and captures through active_episodes
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(context factory, objects) over 2 classes x 3 tiny meshes with the NearestMean stand-in classifiers."""
    from fusion.experiments.context import Context
    from fusion.experiments.data import folder_objects
    from tests.fusion.test_experiments import STANDINS, TINY, mesh_folder

    root = tmp_path_factory.mktemp("active_tiny")
    objects = folder_objects(mesh_folder(root / "meshes"), None, None)
    return (lambda out, seed=5, classifiers=STANDINS: Context(root / out, seed, TINY, classifiers, progress=False)), objects


def test_active_episodes_seeds_episode_e_with_seed_plus_e(tiny, monkeypatch):
    """episodes=3: three runs per object and policy, the policies and the sensor noise of episode e seeded with
    seed + e; episode 0 is exactly the one-episode run, and the camera-alone decision comes from episode 0."""
    from fusion.experiments import active

    context, objects = tiny
    made, ran = [], []
    real_make, real_run = active.make_policy, active.run_episode

    def make(name, seed, **kw):
        made.append((name, seed))
        return real_make(name, seed, **kw)

    def run(*args, seed, **kw):
        ran.append(seed)
        return real_run(*args, seed=seed, **kw)

    monkeypatch.setattr(active, "make_policy", make)
    monkeypatch.setattr(active, "run_episode", run)
    ctx = context("seeds")
    ctx.workers = 1  # the objects in this process, where the spies are
    options = {"policies": ("random", "information"), "max_touches": 2, "candidates": 3, "variants": 1,
               "per_fold": 1}
    three = active.active_episodes(ctx, objects, episodes=3, **options)
    assert three["episodes"] == 3
    assert set(made) == {(p, 5 + e) for p in ("random", "information") for e in range(3)}
    assert sorted(set(ran)) == [5, 6, 7]
    for row in three["objects"]:
        for p in ("random", "information"):
            assert len(active._runs(row, p)) == 3
    assert any(run["posteriors"] != active._runs(row, "random")[0]["posteriors"]
               for row in three["objects"] for run in active._runs(row, "random")[1:])
    one = active.active_episodes(ctx, objects, episodes=1, **options)
    assert [r["object"] for r in one["objects"]] == [r["object"] for r in three["objects"]]
    for a, b in zip(one["objects"], three["objects"]):
        assert "more_runs" not in a["policies"]["random"]
        assert a["visual_decision"] == b["visual_decision"]
        for p in ("random", "information"):
            assert a["policies"][p]["posteriors"] == b["policies"][p]["posteriors"]


def test_the_visual_models_saliency_is_computed_once_per_object_for_every_episode(tiny, monkeypatch):
    """The camera's view is looked at once: 3 saliency episodes per object cost one multiview saliency of its visual
    model (seeded by the run's seed), and each episode still draws its own pair order from those interest points."""
    from fusion.experiments import active
    from perception import saliency as attention

    context, objects = tiny
    looked = []
    real = attention.saliency

    def spy(model, method, **kw):
        looked.append((model.name, method, kw.get("seed")))
        return real(model, method, **kw)

    monkeypatch.setattr(attention, "saliency", spy)
    ctx = context("saliency-once")
    ctx.workers = 1  # the objects in this process, where the spy is
    out = active.active_episodes(ctx, objects, policies=("saliency",), max_touches=3, episodes=3, per_fold=1)
    names = [f"{row['object']}@visual" for row in out["objects"]]
    assert len(names) >= 2
    assert looked == [(name, "multiview", 5) for name in names]
    assert all(row["saliency_s"] > 0 for row in out["objects"])
    orders = [[run["posteriors"] for run in active._runs(row, "saliency")] for row in out["objects"]]
    assert any(o[0] != o[1] or o[0] != o[2] for o in orders)  # the episodes' pair orders differ
    timing = active.summarize(out)["timing"][0]
    assert timing["policy"] == "saliency" and timing["saliency_per_object_s"] > 0


def test_active_episodes_give_the_same_records_on_one_worker_or_two(tiny):
    """The objects run side by side on the run's workers; each policy's draws are seeded by the object's visual
    model and the step, so the records (all but the timings) are the same as in one process, object by object."""
    from fusion.experiments import active

    context, objects = tiny
    timing = {"planning_s", "touching_s", "classifying_s", "seconds", "saliency_s"}

    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in timing}
        return [strip(v) for v in x] if isinstance(x, list) else x

    options = {"policies": ("random", "saliency", "information"), "max_touches": 3, "candidates": 3, "variants": 1,
               "episodes": 2}
    records = []
    for workers in (1, 2):
        ctx = context(f"workers{workers}")
        ctx.workers = workers
        records.append(active.active_episodes(ctx, objects, **options))
    assert len(records[0]["objects"]) == len(objects)
    assert strip(records[0]) == strip(records[1])
    assert records[0]["objects"][0]["policies"]["random"]["planning_s"]  # the timings are there


@pytest.mark.parametrize("first", ["active", "unseen"])
def test_the_active_part_shares_the_unseen_parts_fold_models(tiny, first):
    """The active part's fold models are the unseen-objects part's (the same store, folds and classifier): whichever
    part runs first trains one model per fold, on exactly that fold's training objects, and the other reads them."""
    from fusion.experiments import active
    from fusion.experiments.protocol import pooled_folds, unseen_objects
    from tests.fusion.test_experiments import recorder

    context, objects = tiny
    fits = []
    ctx = context(f"shared-{first}", classifiers={"nm": recorder(fits)})
    parts = {"active": lambda: active.active_episodes(ctx, objects, classifier="nm", policies=("random",),
                                                      max_touches=1, per_fold=1),
             "unseen": lambda: unseen_objects(ctx, objects)}
    parts[first]()
    ds, _ = ctx.store(objects, strategies=ctx.sizes.strategies, contours=ctx.sizes.unseen_contours)
    folds = pooled_folds(ctx, ds, ctx.sizes.strategies, ctx.sizes.unseen_folds)
    expected = [(len(train), {ds.object_names[j] for j in np.unique(ds.object_ids[train])}) for train, _ in folds]
    assert fits == expected
    parts["unseen" if first == "active" else "active"]()
    assert fits == expected  # read, not trained again


def test_a_damaged_shared_fold_model_is_trained_again(tiny):
    """A fold model file gone bad while the unseen part's predictions of it are still cached: the active part trains
    that fold's model again (a warning says why) instead of failing, and the others are read."""
    from fusion.experiments import active
    from fusion.experiments.protocol import fold_folder, unseen_objects
    from tests.fusion.test_experiments import recorder

    context, objects = tiny
    fits = []
    ctx = context("damaged", classifiers={"nm": recorder(fits)})
    unseen_objects(ctx, objects)
    assert len(fits) == 3
    damaged = fold_folder(ctx, "unseen", ctx.sizes.strategies, 1) / "nm.vtm"
    damaged.write_bytes(damaged.read_bytes()[:100])
    result = active.active_episodes(ctx, objects, classifier="nm", policies=("random",), max_touches=1, per_fold=1)
    assert len(fits) == 4 and fits[3] == fits[1]  # fold 2 again, on the same training objects
    assert len(result["objects"]) == 3


def test_a_test_object_whose_capture_fails_is_left_out_and_listed(tiny, monkeypatch):
    """With the camera in the loop, an object whose capture finds nothing gets no record and is listed in
    capture_failures; the others are recorded."""
    from fusion.active import noisy_copy
    from fusion.experiments import active
    from perception.errors import InvalidMeshError

    context, objects = tiny
    failing = min(str(p) for p, _ in objects)

    def camera(captures, spec, true, seed):
        if spec.path == failing:
            raise InvalidMeshError(f"{spec.name}: no object on the table")
        return noisy_copy(true, 1.0, seed=seed), true

    monkeypatch.setattr(active, "camera_models", camera)
    ctx = context("captures")
    ctx.workers = 1  # in this process, where the stand-in camera is
    result = active.active_episodes(ctx, objects, policies=("random",), max_touches=2, visual="camera")
    names = [r["object"] for r in result["objects"]]
    assert len(result["capture_failures"]) == 1 and result["capture_failures"][0] not in names
    assert len(names) == len(objects) - 1


@pytest.mark.parametrize("bad", [0, -1, 2.5, "2", True, None, np.int64(0), 10**12])
def test_active_episodes_refuses_bad_episodes_before_any_work(bad):
    """Refused before the context is touched (ctx=None would fail otherwise); a count beyond the touch limit too."""
    from fusion.experiments import active

    with pytest.raises(InvalidArgumentError, match="episodes"):
        active.active_episodes(None, [], episodes=bad)


@pytest.mark.parametrize("options, match", [
    ({"per_fold": 0}, "per_fold"), ({"per_fold": -1}, "per_fold"), ({"per_fold": 1.5}, "per_fold"),
    ({"per_fold": True}, "per_fold"),
    ({"candidates": 0}, "candidates"), ({"variants": 0}, "variants"), ({"candidates": 2.5}, "candidates"),
    ({"noise_mm": -1.0}, "noise_mm"), ({"noise_mm": float("nan")}, "noise_mm"), ({"noise_mm": "1"}, "noise_mm"),
    ({"policies": ()}, "policies"), ({"policies": ("random", "greedy")}, "greedy"),
    ({"policies": ("random", "random")}, "twice"), ({"policies": "random"}, "policies"),
    ({"policies": {"random"}}, "policies"), ({"policies": 5}, "policies"), ({"noise_mm": True}, "noise_mm"),
    ({"noise_mm": 10**400}, "noise_mm"), ({"noise_mm": 1e300}, r"noise_mm must be a finite number in \[0, 1000\]"),
    # the budget is recorded with the result and named in the report, whichever policies run
    ({"policies": ("random",), "candidates": 0}, "candidates"),
    ({"policies": ("random",), "variants": "2"}, "variants"),
])
def test_active_episodes_refuses_bad_options_before_any_work(options, match):
    """Every option is checked before the store is made or a model fitted (ctx=None would fail otherwise): a
    negative per_fold silently dropped each fold's last object, and a bad candidate count or policy name surfaced
    only in the first episode, after the stores and fits."""
    from fusion.experiments import active

    with pytest.raises(InvalidArgumentError, match=match):
        active.active_episodes(None, [], **options)


@pytest.mark.parametrize("options", [
    {"noise_mm": 0}, {"noise_mm": np.float32(0.0)}, {"noise_mm": 1000}, {"per_fold": 1}, {"per_fold": np.int64(2)},
    {"policies": ["random"]}, {"candidates": np.int64(1), "variants": 1},
])
def test_active_options_at_their_bounds_pass_the_checks(options):
    """The lowest values allowed (no noise, one object per fold, one candidate) and numpy scalars get past the
    checks: the run then fails only on ctx=None, at the store."""
    from fusion.experiments import active

    with pytest.raises(AttributeError):
        active.active_episodes(None, [], **options)


def test_active_options_come_back_as_plain_python_values():
    """numpy scalars pass the checks but go on as Python numbers: the result is written as JSON, where numpy's
    integers and float32 would be written as strings."""
    from fusion.experiments.active import _check_options

    checked = _check_options(["random"], np.int64(3), np.int32(1), np.float32(0.5), np.int64(2))
    assert checked == (("random",), 3, 1, 0.5, 2)
    assert [type(x) for x in checked] == [tuple, int, int, float, int]
    assert _check_options(("random",), 3, 1, 1, None)[3:] == (1.0, None)
    noise = _check_options(("random",), 3, 1, -0.0, None)[3]  # --noise-mm -0.0: recorded and used as 0.0
    assert noise == 0.0 and np.copysign(1.0, noise) == 1.0


def test_active_episodes_refuses_an_unknown_classifier_before_the_store():
    """--classifier bogus was refused only after the store had been generated."""
    from types import SimpleNamespace

    from fusion.experiments import active
    from tests.fusion.test_experiments import STANDINS, TINY

    def store(*args, **kwargs):
        raise AssertionError("the store was asked for")

    ctx = SimpleNamespace(sizes=TINY, classifiers=STANDINS, store=store)
    with pytest.raises(InvalidArgumentError, match="bogus"):
        active.active_episodes(ctx, [], classifier="bogus")


def test_summary_of_no_objects_says_so():
    from fusion.experiments import active
    from perception.errors import DatasetError

    with pytest.raises(DatasetError, match="no test object"):
        active.summarize({**episodes(), "objects": []})


def test_summary_of_one_object_says_why_it_cannot_pair_it():
    """One object (every other capture failed) cannot be paired against random: said so (a DatasetError naming
    the count), not paired_over_objects' bare refusal of its arrays; random alone is summarized."""
    from perception.errors import DatasetError

    one = {**episodes(), "objects": episodes()["objects"][:1]}
    with pytest.raises(DatasetError, match="1 test object"):
        summarize(one)
    alone = {**one, "objects": [{**r, "policies": {"random": r["policies"]["random"]}} for r in one["objects"]]}
    assert summarize(alone)["n_objects"] == 1


def test_active_episodes_refuses_captures_without_the_camera():
    from fusion.experiments import active

    with pytest.raises(InvalidArgumentError, match="camera"):
        active.active_episodes(None, [], visual="noisy", train_on_captures=True)


def test_train_on_captures_learns_from_the_training_objects_captures_only(tiny, monkeypatch):
    """Each fold's classifier is trained on the store's training sequences plus touches on the captures of exactly
    the fold's training objects (never a test object), each capture counted as its own object (one group for every
    grouped split); the model is cached apart from the mesh-only one and trained again when what the captures are
    made with changes."""
    from fusion.active import noisy_copy
    from fusion.experiments import active
    from tests.fusion.test_experiments import recorder

    context, objects = tiny
    fits, captured = [], []

    def camera(ctx, spec, true, seed, views=active.CAMERA_VIEWS):  # a fast stand-in for the OAK-D capture
        return noisy_copy(true, 1.0, seed=seed), true

    real_capture = active.capture_batch

    def capture(ctx, names, *args):
        captured.append(list(names))
        return real_capture(ctx, names, *args)

    monkeypatch.setattr(active, "camera_models", camera)
    monkeypatch.setattr(active, "capture_batch", capture)
    ctx = context("captures", classifiers={"nm": recorder(fits)})
    options = {"policies": ("random",), "max_touches": 1, "per_fold": 1, "visual": "camera"}
    plain = active.active_episodes(ctx, objects, **options)
    n_plain = len(fits)
    assert n_plain == 3 and not captured and plain["train_on_captures"] is False
    result = active.active_episodes(ctx, objects, train_on_captures=True, **options)
    assert result["train_on_captures"] is True
    assert len(fits) == 2 * n_plain  # a model of its own: the mesh-only models are not reused
    ds, _ = ctx.store(objects, strategies=ctx.sizes.strategies, contours=ctx.sizes.unseen_contours)
    folds = ds.kfold_by_object(ctx.sizes.unseen_folds, seed=ctx.seed)
    for (train, test), names, (n_seq, fitted) in zip(folds, captured, fits[n_plain:]):
        train_names = {ds.object_names[j] for j in np.unique(ds.object_ids[train])}
        assert set(names) == train_names  # captures of the training objects, none of the test objects
        assert fitted == train_names  # a capture's touches belong to its object
        assert n_seq == len(train) + len(train_names) * ctx.sizes.unseen_contours
    active.active_episodes(ctx, objects, train_on_captures=True, **options)  # same settings: cached
    assert len(fits) == 2 * n_plain
    active.active_episodes(ctx, objects, **options)  # ... and the mesh-only models were not overwritten
    assert len(fits) == 2 * n_plain
    monkeypatch.setattr(active, "SMOOTH_ITERATIONS", 3)  # other smoothing of the captures: trained again
    active.active_episodes(ctx, objects, train_on_captures=True, **options)
    assert len(fits) == 3 * n_plain


def test_active_part_file_names(monkeypatch):
    from types import SimpleNamespace

    from fusion.experiments import active
    from fusion.experiments.config import QUICK

    names = []
    ctx = SimpleNamespace(sizes=QUICK, seed=0,
                          cached_part=lambda name, record, compute: names.append(name) or episodes())
    summary = active.active_part(ctx, [], visual="camera", train_on_captures=True)
    assert names == ["active_camera_captures"] and summary["episodes"] == "parts/active_camera_captures.json"
    active.active_part(ctx, [], visual="camera", classifier="cnn")
    assert names[-1] == "active_camera_cnn"


def test_cli_passes_episodes_and_train_on_captures(tmp_path, monkeypatch):
    from fusion.experiments import active, data

    seen = {}

    def part(ctx, objects, **options):
        seen.update(options)
        return {**active.summarize(episodes()), "episodes": "parts/x.json"}

    monkeypatch.setattr(active, "active_part", part)
    monkeypatch.setattr(data, "folder_objects", lambda *a, **k: [])
    active.main(["--data", str(tmp_path), "--out", str(tmp_path / "out"), "--quick", "--visual", "camera",
                 "--episodes", "4", "--train-on-captures"])
    assert seen["episodes"] == 4 and seen["train_on_captures"] is True and seen["visual"] == "camera"
    assert (tmp_path / "out" / "report_camera_captures.md").is_file()


def test_render_markdown_mentions_episodes_only_when_several():
    summary = summarize(episodes())
    assert summary["episodes_per_object"] == 1 and "episodes per object" not in render_markdown(summary)


def test_captures_are_smoothed_as_the_planner_smooths():
    from fusion.active.policies import SMOOTH_ITERATIONS, InformationPolicy

    assert InformationPolicy().smooth_iterations == SMOOTH_ITERATIONS


def test_timings_count_every_episode():
    result = episodes()
    for row in result["objects"]:
        extra = _policy(["a", "a"], [0.6, 0.8])
        extra["planning_s"] = [0.6, 0.03]
        row["policies"]["random"]["more_runs"] = [extra]
    timing = {t["policy"]: t for t in summarize(result)["timing"]}
    assert timing["random"]["planning_mean_s"] == pytest.approx((0.2 + 0.01 + 0.6 + 0.03) / 4)
    assert timing["random"]["planning_first_s"] == pytest.approx(0.4)  # median of 0.2 (x10) and 0.6 (x10)


def test_module_runner_refuses_bad_input_in_one_line(tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "fusion.experiments.active", "--data", str(tmp_path / "none"),
                           "--out", str(tmp_path / "out")], check=False, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    expected = (f"python -m fusion.experiments.active: error: {tmp_path / 'none'}: not a folder "
                "(expected <root>/<Class>/<instance>.<ext>)")
    assert done.stderr.strip().splitlines() == [expected]


@pytest.mark.parametrize("argv, named", [
    (["--candidates", "abc"], "--candidates"), (["--noise-mm", "x"], "--noise-mm"),
    (["--visual", "lidar"], "--visual"),
    (["--seed", "-1"], "--seed"), (["--seed", str(2**32)], "--seed"),
    (["--seed", str(2**31), "--visual", "camera"], "--seed"),
    # the options' own checks name the flag, and come before the (here empty) data folder is read
    (["--noise-mm", "1e300"], "--noise-mm must be a finite number in [0, 1000] mm"),
    (["--noise-mm", "-1"], "--noise-mm must be"), (["--per-fold", "0"], "--per-fold must be"),
    (["--candidates", "0"], "candidates must be"), (["--policies", "random,random"], "named twice"),
])
def test_module_runner_refuses_bad_options_in_one_line(tmp_path, argv, named, capsys):
    """A value argparse refuses is one line (not the 13-line usage); a seed outside what NumPy's legacy
    seeding and scikit-learn take (32 bits; 31 with the camera, Open3D's C int) is refused before the store is
    generated (2**32 failed in the first fit with a traceback). In this process, through what ``python -m`` runs
    (:func:`cli`; the test above runs the module itself)."""
    from fusion.experiments.active import cli

    try:
        status = cli(["--data", str(tmp_path), "--out", str(tmp_path / "out"), *argv])
    except SystemExit as exc:  # argparse's own refusals
        status = exc.code
    assert status == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("python -m fusion.experiments.active: error:")
    assert named in lines[0]
    assert not (tmp_path / "out").exists()


# runpy warns that the module is imported already: it is, by this test process (``python -m`` starts without it)
@pytest.mark.filterwarnings("ignore:.*found in sys.modules after import:RuntimeWarning")
def test_module_runner_runs_the_package_module(monkeypatch):
    """``python -m fusion.experiments.active`` runs the package's copy of the module: jobs built from ``__main__``'s
    classes cannot go to worker processes, and its episodes would run one object after another in one process."""
    import runpy

    from fusion.experiments import active

    calls = []
    monkeypatch.setattr(active, "main", lambda argv=None: calls.append(argv))
    with pytest.raises(SystemExit) as exited:
        runpy.run_module("fusion.experiments.active", run_name="__main__")
    assert calls == [None] and exited.value.code == 0


def test_the_shared_fold_models_train_on_the_workers_and_leave_the_unseen_predictions(tiny):
    """fold_models trains through ctx.run: with two workers no fit runs in this process, and each fold's upright
    test predictions are cached for the unseen part (which then only reads them)."""
    from fusion.experiments import active
    from fusion.experiments.protocol import kfold_tasks
    from tests.fusion.test_experiments import CALLS, CountingMean

    context, objects = tiny
    ctx = context("on-workers", classifiers={"count": CountingMean})
    ctx.workers = 2
    CALLS.update(fit=0, predict=0)
    models = active.fold_models(ctx, objects, {"count": CountingMean})
    assert CALLS["fit"] == 0  # trained on the workers
    assert len(models) == ctx.sizes.unseen_folds and all(isinstance(m["count"], CountingMean) for m in models)
    sizes = ctx.sizes
    ds, record = ctx.store(objects, strategies=sizes.strategies, contours=sizes.unseen_contours)
    tasks = kfold_tasks(ctx, "unseen", (ds, record, ds, record), tuple(sizes.strategies), {"count": CountingMean},
                        sizes.unseen_folds, "upright")
    assert all(task.cached() is not None for task in tasks.values())


def test_each_test_object_meets_the_model_of_its_own_fold(tiny, monkeypatch):
    """The model an object's episodes run on is the saved unseen-part model of the fold that tests that object
    (never one trained on it)."""
    from fusion.base import load_model
    from fusion.experiments import active
    from fusion.experiments.protocol import fold_folder, pooled_folds

    context, objects = tiny
    ctx = context("own-fold")
    ctx.workers = 1  # the episodes in this process, where the spy is
    seen = []
    real_run = active.run_episode
    monkeypatch.setattr(active, "run_episode", lambda true, vis, model, *a, **k: seen.append((true.name, model))
                        or real_run(true, vis, model, *a, **k))
    active.active_episodes(ctx, objects, classifier="nm", policies=("random",), max_touches=1)
    sizes = ctx.sizes
    ds, _ = ctx.store(objects, strategies=sizes.strategies, contours=sizes.unseen_contours)
    fold_of = {ds.object_names[o]: i for i, (_, test) in
               enumerate(pooled_folds(ctx, ds, sizes.strategies, sizes.unseen_folds)) for o in ds.object_ids[test]}
    saved = [load_model(fold_folder(ctx, "unseen", sizes.strategies, i) / "nm.vtm") for i in range(sizes.unseen_folds)]
    assert len({name for name, _ in seen}) == len(fold_of)
    for name, model in seen:
        assert np.array_equal(model.mu_, saved[fold_of[name]].mu_), name


def test_more_training_contours_keep_the_unseen_parts_fold_models(tiny):
    """With ``unseen_train_contours`` set the unseen part trains on a store of its own: the active part must not
    overwrite the unseen part's fold models or upright predictions (which the noise part and later runs read), and
    a rerun of both parts trains nothing."""
    import json

    from fusion.experiments import active
    from fusion.experiments.context import Context
    from fusion.experiments.protocol import fold_folder, unseen_objects
    from tests.fusion.test_experiments import recorder

    context, objects = tiny
    fits = []
    base = context("more-train")
    ctx = Context(base.out, base.seed, base.sizes.with_(unseen_train_contours=15), {"nm": recorder(fits)},
                  progress=False)
    unseen_objects(ctx, objects)
    folder = fold_folder(ctx, "unseen", ctx.sizes.strategies, 0)
    before = {f.name: f.read_bytes() for f in folder.iterdir() if f.suffix in (".json", ".npz")}
    active.active_episodes(ctx, objects, classifier="nm", policies=("random",), max_touches=1, per_fold=1)
    after = {f.name: f.read_bytes() for f in folder.iterdir() if f.name in before}
    assert after == before, json.loads((folder / "nm.json").read_text())["record"]
    fits.clear()
    unseen_objects(ctx, objects)
    active.active_episodes(ctx, objects, classifier="nm", policies=("random",), max_touches=1, per_fold=1)
    assert fits == []


def test_a_capture_of_other_code_is_made_again(tmp_path, monkeypatch):
    """The capture cache is named after the generation code: a capture made by other code (another reconstruction)
    is not read as this code's; the same code reads its own file back."""
    import tactile.captures
    import tactile.dataset
    from fusion.experiments import active
    from tactile.dataset import ObjectSpec

    spec = ObjectSpec("mug/0", "mug", catalogue=("mug", 0))
    made, capture = [], tactile.captures.virtual_capture  # camera_models imports it when called: patched at home
    monkeypatch.setattr(tactile.captures, "virtual_capture", lambda *a, **k: made.append(1) or capture(*a, **k))
    first, _ = active.camera_models(tmp_path, spec, spec.load(), 0)
    again, _ = active.camera_models(tmp_path, spec, spec.load(), 0)
    assert len(made) == 1 and np.array_equal(first.vertices, again.vertices)  # read back
    monkeypatch.setattr(tactile.dataset, "generation_code_version", lambda: "0123456789abcdef")
    active.camera_models(tmp_path, spec, spec.load(), 0)
    assert len(made) == 2 and len(list(tmp_path.glob("*.npz"))) == 2
