"""Replaying next-touch criteria over a candidate bank: the information criterion's replay is the episode that
run_episode runs with the information policy (the same planes, posteriors to the bit, misses included), a criterion
sees no untouched plane's real reading, the deciding classifier does not choose, and bad input is refused."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from fusion.active import InformationPolicy, make_policy, noisy_copy, run_episode
from fusion.active.policies import ActiveState, simulated_outcomes
from fusion.active.replay import CandidateBank, build_bank, hindsight, information_criterion, replay
from fusion.decide import fuse_touches
from perception.errors import InvalidArgumentError
from perception.shapes import make_object
from tactile.contours import Plane
from tactile.sensor import FSRSensor

CLASSES = np.array(["a", "b", "c"], dtype=object)


class GapClassifier:
    """A fitted-classifier stand-in that reads the frames and the plane: softmax of fixed weights times (mean gap,
    share of taxels in contact, |plane normal z|), so different contours read differently."""

    classes_ = CLASSES
    probes = 8
    WEIGHTS = np.array([[1.5, -2.0, 3.0], [-0.5, 4.0, -1.0], [0.2, 0.5, 0.5]])

    def __init__(self, sensor=None):
        self._sensor = sensor or FSRSensor(rows=8, cols=8)

    def sensor(self):
        return self._sensor

    def predict_proba(self, batch):
        frames = np.asarray(batch.frames, dtype=np.float64)
        features = np.stack([frames.mean(axis=(1, 2, 3)), (frames < 0.5).mean(axis=(1, 2, 3)),
                             np.abs(batch.plane_normals[:, 2])], axis=1)
        logits = features @ self.WEIGHTS.T
        p = np.exp(logits - logits.max(axis=1, keepdims=True))
        return p / p.sum(axis=1, keepdims=True)


class TiltClassifier(GapClassifier):
    """Reads the plane's tilt only: another classifier over the same classes."""

    def predict_proba(self, batch):
        z = np.abs(batch.plane_normals[:, 2])
        return np.stack([0.2 + 0.6 * z, 0.8 - 0.6 * z, np.full_like(z, 0.3)], axis=1) / 1.3


@pytest.fixture(scope="module")
def objects():
    mug, box = make_object("mug", 0), make_object("box", 0)
    return mug, box, noisy_copy(mug, 0.5, seed=1), noisy_copy(box, 0.5, seed=2)


def _policy(seed):
    return InformationPolicy(seed, candidates=5, variants=2)


@pytest.mark.parametrize("seed", [0, 3])
@pytest.mark.parametrize("which", [0, 1])
def test_information_replay_is_the_episode(objects, seed, which):
    true, visual = objects[which], objects[2 + which]
    clf = GapClassifier()
    # 7 touches of 5 candidates: the last two touch the best candidate again, as the policy does
    episode = run_episode(true, visual, clf, _policy(seed), max_touches=7, seed=11)
    bank = build_bank(true, visual, {"gap": clf}, _policy(seed))
    order, posteriors = replay(bank, information_criterion("gap"), "gap", max_touches=7)
    assert len(set(order)) < len(order) == 7
    for plane, m in zip(episode.planes, order, strict=True):
        assert np.array_equal(plane.point, bank.planes[m].point) and np.array_equal(plane.normal, bank.planes[m].normal)
    assert np.array_equal(posteriors, episode.posteriors)
    assert [str(CLASSES[i]) for i in posteriors.argmax(axis=1)] == episode.decisions()


def test_missed_planes_read_uniform_as_in_the_episode(objects):
    mug, _, visual, _ = objects
    far = dataclasses.replace(mug, vertices=mug.vertices + 1000.0, name="far mug")  # no plane of the visual cuts it
    clf = GapClassifier()
    bank = build_bank(far, visual, {"gap": clf}, _policy(0))
    assert bank.missed.all()
    assert np.array_equal(bank.real["gap"], np.full((5, 3), 1 / 3))
    episode = run_episode(far, visual, clf, _policy(0), max_touches=3)
    order, posteriors = replay(bank, information_criterion("gap"), "gap", max_touches=3)
    assert episode.missed.all() and np.array_equal(posteriors, episode.posteriors)
    assert all(np.array_equal(p.normal, bank.planes[m].normal) for p, m in zip(episode.planes, order, strict=True))


def test_a_criterion_sees_only_touched_readings(objects):
    mug, _, visual, _ = objects
    bank = build_bank(mug, visual, {"gap": GapClassifier(), "tilt": TiltClassifier()}, _policy(1))
    seen = []

    def spy(view):
        seen.append(view)
        return np.arange(len(bank.planes), dtype=np.float64)[::-1]  # touches candidates 0, 1, 2, ... in turn

    order, _ = replay(bank, spy, "gap", max_touches=4)
    assert order == [0, 1, 2, 3]
    for step, view in enumerate(seen):
        assert view.step == step and view.touched.sum() == step
        for name in ("gap", "tilt"):
            assert view.readings[name].shape == (step, 3)
            assert np.array_equal(view.readings[name], bank.real[name][:step])


def test_the_deciding_classifier_does_not_choose(objects):
    mug, _, visual, _ = objects
    bank = build_bank(mug, visual, {"gap": GapClassifier(), "tilt": TiltClassifier()}, _policy(2))
    by_gap, _ = replay(bank, information_criterion("tilt"), "gap", max_touches=4)
    by_tilt, _ = replay(bank, information_criterion("tilt"), "tilt", max_touches=4)
    assert by_gap == by_tilt
    _, posteriors = replay(bank, information_criterion("tilt"), "gap", max_touches=4)
    expected = [fuse_touches(bank.real["gap"][by_gap[:k]], rule="log") for k in range(1, 5)]
    assert np.allclose(posteriors, expected, rtol=0, atol=0)


def test_refusals(objects):
    mug, _, visual, _ = objects
    clf = GapClassifier()
    with pytest.raises(InvalidArgumentError, match="noise-free"):
        build_bank(mug, visual, {"noisy": GapClassifier(FSRSensor(rows=8, cols=8, noise_std=0.1))}, _policy(0))
    other = GapClassifier()
    other.classes_ = np.array(["a", "c", "b"], dtype=object)
    with pytest.raises(InvalidArgumentError, match="one class order"):
        build_bank(mug, visual, {"gap": clf, "other": other}, _policy(0))
    with pytest.raises(InvalidArgumentError, match="another sensor"):
        build_bank(mug, visual, {"gap": clf, "big": GapClassifier(FSRSensor(rows=16, cols=16))}, _policy(0))
    with pytest.raises(InvalidArgumentError, match="non-empty"):
        build_bank(mug, visual, {}, _policy(0))
    with pytest.raises(InvalidArgumentError, match="InformationPolicy"):
        build_bank(mug, visual, {"gap": clf}, make_policy("random"))
    bank = build_bank(mug, visual, {"gap": clf}, _policy(0))
    with pytest.raises(InvalidArgumentError, match="no classifier 'cnn'"):
        replay(bank, information_criterion("gap"), "cnn")
    for budget in (0, -1, 2.5, True):
        with pytest.raises(InvalidArgumentError, match="max_touches"):
            replay(bank, information_criterion("gap"), "gap", max_touches=budget)
    for bad in (lambda view: np.zeros(2), lambda view: np.full(5, np.nan)):
        with pytest.raises(InvalidArgumentError, match="criterion"):
            replay(bank, bad, "gap")


# ---------------------------------------------------------------------------- benchmarks.active_replay
def _hand_bank():
    """Three candidates of an object of class "a": candidate 0 reads "a" (0.9), 1 and 2 read "b" (0.7); the
    simulation makes candidate 0 the one that best confirms the view."""
    real = np.array([[0.9, 0.1], [0.3, 0.7], [0.3, 0.7]])
    sim = np.repeat(np.array([[0.9, 0.1], [0.6, 0.4], [0.6, 0.4]])[:, None, :], 2, axis=1)
    planes = [Plane(np.zeros(3), np.eye(3)[i]) for i in range(3)]
    return CandidateBank("hand", ["a", "b"], planes, {"x": sim}, {"x": real}, np.zeros(3, dtype=bool))


def test_benchmark_scores_against_hand_fused_decisions():
    from benchmarks.active_replay import BUDGET, _random_order, right
    from fusion.active.replay import information_criterion

    rows = [{"object": "hand", "label": "a", "banks": [_hand_bank(), _hand_bank()]}]
    # information: candidate 0 first (right), then 1 (0.27 : 0.07, right), then 2 (0.081 : 0.049, right), then 0 again
    assert right(rows, lambda s: information_criterion("x"), "x").tolist() == [[1.0] * BUDGET]
    # random order: seed s touches the candidates in the order of np.random.default_rng(1000 + s).permutation(3)
    expected = []
    for s in range(2):
        order = np.random.default_rng(1000 + s).permutation(3).tolist()
        first = order[0]
        k2 = 0 in order[:2]  # with candidate 0, (0.9 * 0.3) : (0.1 * 0.7) names "a"; without it, "b"
        expected.append([first == 0, k2, True])  # all three: 0.081 : 0.049
    got = right(rows, lambda s: _random_order(1000 + s), "x")
    assert got[0, :3].tolist() == np.mean(expected, axis=0).tolist()


# ---------------------------------------------------------------------------- ties, fallbacks, caches, CLI
def _bank(m=4):
    real = np.tile([0.6, 0.4], (m, 1))
    return CandidateBank("h", ["a", "b"], [Plane(np.zeros(3), np.eye(3)[i % 3]) for i in range(m)],
                         {"x": np.full((m, 2, 2), 0.5)}, {"x": real}, np.zeros(m, dtype=bool))


def test_ties_go_to_the_first_and_a_full_pass_touches_the_best_again():
    bank = _bank(3)
    assert replay(bank, lambda v: np.zeros(3), "x", 5)[0] == [0, 1, 2, 0, 0]          # R12
    # steps 0-2 touch 2, 1, 0; then every candidate is touched: the best *now* (1), not the first touched (2)
    crit = lambda v: np.array([1.0, 2.0, 3.0]) if v.step < 3 else np.array([0.0, 5.0, 1.0])
    assert replay(bank, crit, "x", 5)[0] == [2, 1, 0, 1, 1]                             # R3


def test_untouched_candidates_all_scored_minus_inf_fall_back_to_the_best():         # R4 (documented "or scored -inf")
    bank = _bank(3)
    crit = lambda v: np.full(3, -np.inf) if v.touched.any() else np.array([0.0, 1.0, 2.0])
    assert replay(bank, crit, "x", 3)[0] == [2, 2, 2]


def test_plus_inf_scores_are_the_highest_not_a_reason_to_repeat():                 # hostile: fails today
    assert replay(_bank(3), lambda v: np.full(3, np.inf), "x", 4)[0] == [0, 1, 2, 0]


def test_refusals_more(objects):                                                     # R9, R17
    mug, _, visual, _ = objects
    with pytest.raises(InvalidArgumentError, match="dead taxels"):
        build_bank(mug, visual, {"d": GapClassifier(FSRSensor(rows=8, cols=8, dead_taxel_rate=0.2))}, _policy(0))
    few = GapClassifier()
    few.probes = 4
    with pytest.raises(InvalidArgumentError, match="probe count"):
        build_bank(mug, visual, {"gap": GapClassifier(), "few": few}, _policy(0))


@pytest.mark.parametrize("weight", [0.0, 4.0])
def test_visual_weight_is_the_policys(objects, weight):                              # R13
    true, visual = objects[0], objects[2]
    policy = lambda: InformationPolicy(0, candidates=5, variants=2, visual_weight=weight)
    episode = run_episode(true, visual, GapClassifier(), policy(), max_touches=5)
    bank = build_bank(true, visual, {"gap": GapClassifier()}, policy())
    order, posteriors = replay(bank, information_criterion("gap", visual_weight=weight), "gap", 5)
    assert [bank.planes[m].normal.tolist() for m in order] == [p.normal.tolist() for p in episode.planes]
    assert np.array_equal(posteriors, episode.posteriors)


class Spy(GapClassifier):
    """Records every batch it reads (size, labels)."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def predict_proba(self, batch):
        self.calls.append((len(batch.frames), batch.labels.tolist()))
        return super().predict_proba(batch)


def test_one_batch_per_variant_and_per_real_touch_and_no_labels(objects):              # R5, R7, P2
    box = dataclasses.replace(objects[1], label="a")  # a label the classifier knows: it must still not be read
    spy = Spy()
    bank = build_bank(box, objects[3], {"spy": spy}, _policy(0))
    m = len(bank.planes)
    assert [n for n, _ in spy.calls] == [m, m] + [1] * int((~bank.missed).sum())
    assert all(label == -1 for _, labels in spy.calls for label in labels)


def test_candidates_per_visual_model_and_outcomes_per_classifier(objects):            # P1, P5
    _, _, v1, v2 = objects
    shared = _policy(0)
    for visual in (v1, v2, v1):
        assert [p.normal.tolist() for p in shared.candidate_planes(ActiveState(visual, GapClassifier()))] == \
               [p.normal.tolist() for p in _policy(0).candidate_planes(ActiveState(visual, GapClassifier()))]
    gap, tilt = GapClassifier(), TiltClassifier()
    for clf in (gap, tilt):
        planes, outcomes = shared.simulated(ActiveState(v1, clf))
        fresh = _policy(0)
        expected = simulated_outcomes(clf, fresh.simulated_touches(ActiveState(v1, clf), planes))
        assert np.array_equal(outcomes, expected)


@pytest.mark.parametrize("seed", range(1000, 1006))
def test_random_order_is_the_seeded_permutation(seed):                                 # B1, B2
    from benchmarks.active_replay import _random_order
    order, _ = replay(_bank(5), _random_order(seed), "x", 5)
    assert order == np.random.default_rng(seed).permutation(5).tolist()


def _pair_bank():
    """Four candidates read by two classifiers that disagree on which candidate to touch first."""
    x_real = np.array([[0.9, 0.1], [0.3, 0.7], [0.4, 0.6], [0.2, 0.8]])
    y_real = np.array([[0.5, 0.5], [0.8, 0.2], [0.1, 0.9], [0.6, 0.4]])
    x_sim = np.repeat(np.array([[0.9, 0.1], [0.6, 0.4], [0.6, 0.4], [0.5, 0.5]])[:, None], 2, axis=1)
    y_sim = np.repeat(np.array([[0.5, 0.5], [0.4, 0.6], [0.6, 0.4], [0.1, 0.9]])[:, None], 2, axis=1)
    return CandidateBank("pair", ["a", "b"], [Plane(np.zeros(3), np.eye(3)[i % 3]) for i in range(4)],
                         {"x": x_sim, "y": y_sim}, {"x": x_real, "y": y_real}, np.zeros(4, dtype=bool))


def test_screen_rows():                                                                 # B5, B6
    from benchmarks.active_replay import _random_order, right, screen
    rows = [{"object": f"o{i}", "label": label, "banks": [_pair_bank()] * 3} for i, label in enumerate("aa")]
    result = screen(rows, ["x", "y"])
    got = {(r["planner"], r["decider"]): r["accuracy"] for r in result["table"]}
    for decide in ("x", "y"):
        reference = right(rows, lambda s: _random_order(1000 + s), decide)
        assert got[("random order", decide)] == reference.mean(0).tolist()
        for planner in ("x", "y"):
            acc = right(rows, lambda s, p=planner: information_criterion(p), decide)
            assert got[(planner, decide)] == acc.mean(0).tolist()
        assert got[("hindsight", decide)] == right(rows, lambda s: None, decide).mean(0).tolist()
    own = {d: right(rows, lambda s, d=d: information_criterion(d), d)[:, 0] for d in ("x", "y")}
    for diff in result["differences"]:
        if diff["k"] == 1:
            planner = diff["planner"]
            mine = right(rows, lambda s, p=planner: None if p == "hindsight" else information_criterion(p),
                         diff["decider"])[:, 0]
            assert diff["vs_own_planner"]["difference"] == pytest.approx((mine - own[diff["decider"]]).mean())


@pytest.mark.parametrize("seeds", ["-1", "99999999999999999999"])
def test_cli_refuses_bad_seeds_before_the_data(seeds, tmp_path, capsys):               # B7; fails today
    from benchmarks.active_replay import main
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--data", str(tmp_path / "absent"), "--seeds=" + seeds])
    err = capsys.readouterr().err.splitlines()[-1]
    assert "--seeds" in err and "not a folder" not in err  # names --seeds, not the missing data folder


def test_cli_refuses_unknown_classifiers_before_the_data(tmp_path, capsys):            # fails today
    from benchmarks.active_replay import main
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--data", str(tmp_path / "absent"), "--classifiers", "foo"])
    assert "foo" in capsys.readouterr().err.splitlines()[-1]


def test_a_hand_made_bank_is_checked():
    good = _bank(3)
    fields = {"object": "h", "classes": ["a", "b"], "planes": good.planes, "simulated": good.simulated,
              "real": good.real, "missed": good.missed}
    for change, words in (({"planes": []}, "at least one plane"), ({"classes": []}, "one class"),
                          ({"real": {"y": good.real["x"]}}, "same classifier names"),
                          ({"real": {"x": good.real["x"][:2]}}, "expected (M, V, C) and (M, C)"),
                          ({"simulated": {"x": np.full((3, 2, 3), 0.5)}}, "expected (M, V, C) and (M, C)"),
                          ({"real": {"x": np.full((3, 2), np.nan)}}, "finite and non-negative"),
                          ({"simulated": {"x": np.full((3, 2, 2), -0.1)}}, "finite and non-negative"),
                          ({"missed": np.zeros(2, dtype=bool)}, "missed must be")):
        with pytest.raises(InvalidArgumentError, match=re.escape(words)):
            CandidateBank(**(fields | change))


@pytest.mark.parametrize("noise", ["-1", "nan", "1e9"])
def test_cli_refuses_bad_noise_before_the_data(noise, tmp_path, capsys):
    from benchmarks.active_replay import main
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--data", str(tmp_path / "absent"), "--noise-mm=" + noise])
    err = capsys.readouterr().err.splitlines()[-1]
    assert "--noise-mm" in err and "not a folder" not in err


def test_bank_job_makes_the_visual_model_with_its_noise(monkeypatch):
    import fusion.active
    from benchmarks.active_replay import BankJob

    seen = []

    class Stop(Exception):
        pass

    def record(true, noise_mm, seed):
        seen.append((true, noise_mm, seed))
        raise Stop

    monkeypatch.setattr(fusion.active, "noisy_copy", record)
    spec = type("Spec", (), {"load": lambda self: "mesh", "name": "o"})()
    for noise in (1.0, 2.5):
        with pytest.raises(Stop):
            BankJob(spec, {}, 17, (0,), noise).run()
    assert seen == [("mesh", 1.0, 17), ("mesh", 2.5, 17)]
    assert BankJob(spec, {}, 17, (0,)).noise_mm == 1.0  # the active part's default


def test_banks_refuse_a_single_test_object_before_any_fit(monkeypatch, tmp_path):
    from benchmarks.active_replay import banks
    from fusion.experiments import active

    monkeypatch.setattr(active, "active_folds", lambda ctx, objects: (None, {}, [(None, {}, [("only", 3)])]))
    monkeypatch.setattr(active, "fold_models", lambda *a, **k: pytest.fail("fitted before refusing"))
    monkeypatch.setattr("fusion.experiments.data.folder_objects", lambda *a, **k: [])
    with pytest.raises(InvalidArgumentError, match="1 test object"):
        banks(tmp_path, tmp_path / "out", ["svm"], (0,), quick=True)


def test_cli_ends_a_project_error_in_one_line(monkeypatch, tmp_path, capsys):
    import benchmarks.active_replay as bench
    from perception.errors import DatasetError

    def broken(*a, **k):
        raise DatasetError("store.zarr: damaged chunk")

    monkeypatch.setattr(bench, "banks", broken)
    (tmp_path / "data").mkdir()
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--out", str(tmp_path / "out"), "--data", str(tmp_path / "data")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["python -m benchmarks.active_replay: error: store.zarr: damaged chunk"]


@pytest.mark.parametrize(("argv", "expected"), [([], 1.0), (["--noise-mm", "2.5"], 2.5)])
def test_cli_passes_noise_mm_to_the_banks_and_records_it(monkeypatch, tmp_path, capsys, argv, expected):
    import json

    import benchmarks.active_replay as bench

    seen = {}

    def fake_banks(data, out, classifiers, seeds, quick, noise_mm=1.0):
        seen["noise_mm"] = noise_mm
        return []

    monkeypatch.setattr(bench, "banks", fake_banks)
    monkeypatch.setattr(bench, "screen", lambda rows, classifiers: {"objects": 0, "table": [], "differences": []})
    monkeypatch.setattr(bench, "machine", dict)
    (tmp_path / "data").mkdir()
    result = bench.main(["--out", str(tmp_path / "out"), "--data", str(tmp_path / "data"), "--json", *argv])
    assert seen["noise_mm"] == expected and result["noise_mm"] == expected
    assert json.loads(capsys.readouterr().out)["noise_mm"] == expected


def test_banks_give_each_job_its_noise(monkeypatch, tmp_path):
    from benchmarks.active_replay import banks
    from fusion.experiments import active, context

    specs = {name: type("Spec", (), {"label": name.upper(), "name": name})() for name in "ab"}
    monkeypatch.setattr(active, "active_folds", lambda ctx, objects: (None, specs, [(None, {}, [("a", 3), ("b", 4)])]))
    monkeypatch.setattr(active, "fold_models", lambda ctx, objects, classifiers: [{"svm": "model"}])
    monkeypatch.setattr("fusion.experiments.data.folder_objects", lambda *a, **k: [])
    jobs = []
    monkeypatch.setattr(context.Context, "run_jobs", lambda self, js, *a, **k: jobs.extend(js) or [["bank"] for _ in js])
    rows = banks(tmp_path, tmp_path / "out", ["svm"], (0,), quick=True, noise_mm=2.5)
    assert [(j.noise_mm, j.noise_seed, j.seeds) for j in jobs] == [(2.5, 3, (0,)), (2.5, 4, (0,))]
    assert all(j.models == {"svm": "model"} for j in jobs)  # the fold's models
    assert rows == [{"object": "a", "label": "A", "banks": ["bank"], "seeds": [0]},
                    {"object": "b", "label": "B", "banks": ["bank"], "seeds": [0]}]


def test_banks_give_each_fold_its_own_models(monkeypatch, tmp_path):
    from benchmarks.active_replay import banks
    from fusion.experiments import active, context

    specs = {name: type("Spec", (), {"label": name.upper(), "name": name})() for name in "abc"}
    monkeypatch.setattr(active, "active_folds", lambda ctx, objects: (
        None, specs, [(None, {}, [("a", 3)]), (None, {}, [("b", 4), ("c", 5)])]))
    monkeypatch.setattr(active, "fold_models", lambda ctx, objects, classifiers: [{"svm": "m1"}, {"svm": "m2"}])
    monkeypatch.setattr("fusion.experiments.data.folder_objects", lambda *a, **k: [])
    jobs = []
    monkeypatch.setattr(context.Context, "run_jobs", lambda self, js, *a, **k: jobs.extend(js) or [["bank"] for _ in js])
    banks(tmp_path, tmp_path / "out", ["svm"], (0,), quick=True)
    assert [(j.noise_seed, j.models) for j in jobs] == [(3, {"svm": "m1"}), (4, {"svm": "m2"}), (5, {"svm": "m2"})]


# ---------------------------------------------------------------------------- the hindsight reference
def test_hindsight_by_hand():
    # pooled: a 0.9 * 0.3 * 0.6 = 0.162 against b 0.1 * 0.7 * 0.4 = 0.028, so "a"; margins ln 9, ln 3/7, ln 1.5
    real = np.array([[0.9, 0.1], [0.3, 0.7], [0.6, 0.4]])
    bank = CandidateBank("hand", ["a", "b"], [Plane(np.zeros(3), np.eye(3)[i]) for i in range(3)],
                         {"x": np.full((3, 1, 2), 0.5)}, {"x": real}, np.zeros(3, dtype=bool))
    order, posteriors = hindsight(bank, "x", 5)
    assert order == [0, 2, 1, 0, 0]
    np.testing.assert_allclose(posteriors[:3, 0], [0.9, 0.54 / 0.58, 0.162 / 0.19], rtol=1e-12)
    np.testing.assert_allclose(posteriors[3, 0], 0.1458 / (0.1458 + 0.0028), rtol=1e-12)  # 0.9^2 * 0.3 * 0.6


def test_hindsight_reads_with_the_log_rules_floor_and_misses_count_uniform():
    # a zero reading is floored at 1e-12 (as the log rule reads it), so one exact 0 for "a" does not outvote the rest
    real = np.array([[0.0, 1.0], [0.99, 0.01], [0.99, 0.01], [0.99, 0.01], [0.5, 0.5]])
    bank = CandidateBank("floor", ["a", "b"], [Plane(np.zeros(3), np.eye(3)[i % 3]) for i in range(5)],
                         {"x": np.full((5, 1, 2), 0.5)}, {"x": real}, np.array([False] * 4 + [True]))
    order, posteriors = hindsight(bank, "x", 5)
    # pooled: 3 ln 99 - ln 1e12 = 13.8 - 27.6 < 0, so "b"; margins: ln 1e12 (0), -ln 99 (1-3), 0 (the miss, 4)
    assert order == [0, 4, 1, 2, 3]
    assert posteriors.argmax(axis=1).tolist() == [1, 1, 1, 1, 1]


def test_hindsight_names_the_pooled_class_whenever_any_k_candidates_do():
    # with two classes, the widest-margin K are the best K subset: checked against every subset of random banks
    from itertools import combinations
    rng = np.random.default_rng(7)
    for _ in range(60):
        m = int(rng.integers(2, 7))
        real = rng.dirichlet([0.7, 0.7], size=m)
        bank = CandidateBank("r", ["a", "b"], [Plane(np.zeros(3), np.eye(3)[i % 3]) for i in range(m)],
                             {"x": np.full((m, 1, 2), 0.5)}, {"x": real}, np.zeros(m, dtype=bool))
        verdict = int(np.log(real).sum(axis=0).argmax())
        _, posteriors = hindsight(bank, "x", m)
        for k in range(1, m + 1):
            reachable = any(np.log(real[list(s)]).sum(axis=0).argmax() == verdict for s in combinations(range(m), k))
            assert (posteriors[k - 1].argmax() == verdict) == reachable


def test_hindsight_refusals():
    bank = _bank(3)
    for decide, touches in (("nope", 3), ("x", 0), ("x", True), ("x", 2.0)):
        with pytest.raises(InvalidArgumentError, match="hindsight"):
            hindsight(bank, decide, touches)
    with pytest.raises(InvalidArgumentError, match="hindsight"):
        hindsight(object(), "x", 3)


def test_the_random_order_of_a_policy_seed_does_not_depend_on_the_other_seeds():
    # a bank replayed as seed 3 reads the random order of seed 3 (1000 + 3) whether the run holds seeds 0-4 or 3
    # alone (it used to be seeded by the bank's position in the run)
    from benchmarks.active_replay import _random_order, right

    bank = _hand_bank()
    alone = [{"object": "hand", "label": "a", "banks": [bank], "seeds": [3]}]
    among = [{"object": "hand", "label": "a", "banks": [bank] * 5, "seeds": [0, 1, 2, 3, 4]}]
    expected = right([{"object": "hand", "label": "a", "banks": [bank]}], lambda s: _random_order(1003), "x")
    assert right(alone, lambda s: _random_order(1000 + s), "x").tolist() == expected.tolist()
    seen = []
    right(among, lambda s: seen.append(s) or _random_order(1000 + s), "x")
    assert seen == [0, 1, 2, 3, 4]
    order_3 = np.random.default_rng(1003).permutation(3).tolist()
    order_0 = np.random.default_rng(1000).permutation(3).tolist()
    assert order_3 != order_0  # the check has teeth: the two seeds touch in other orders
