"""Several calibrated models deciding "unknown" together (:func:`fusion.openset.joint_decide`): conformal p-values
and the joint threshold against hand-computed values, and a toy problem where each model alone misses one far
cluster (it lies among known readings in that model's feature) while the two together reject both."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest

from fusion.base import load_model
from fusion.openset import (
    UNKNOWN,
    calibrate,
    conformal_log_p,
    decide,
    joint_decide,
    joint_log_p,
    joint_scores,
    joint_threshold,
)
from perception.errors import DatasetError, InvalidArgumentError, ModelFileError, NotFittedError
from tests.fusion._synthetic import circle_batch
from tests.fusion.test_openset import MeanClassifier


class TaxelClassifier(MeanClassifier):
    """The open-set tests' stand-in reading one taxel (its mean over the probes) instead of the whole pad."""

    def __init__(self, taxel: int = 0, width: float = 1.0):
        self.taxel = taxel
        self.width = width

    def _x(self, batch) -> np.ndarray:
        return batch.frames.reshape(len(batch), batch.frames.shape[1], -1)[:, :, self.taxel].astype(np.float64).mean(1)


def two_taxel_batch(centres, objects_per_class=8, per_object=6, seed=0, class_names=None):
    """Sequences on a 2 x 2 pad whose taxel 0 reads near a class's first centre and taxel 3 near its second (object
    offsets + sequence noise, independent per taxel); the other taxels read 0."""
    rng = np.random.default_rng(seed)
    rows, labels, objects = [], [], []
    for c, (a, b) in enumerate(centres):
        for _ in range(objects_per_class):
            offset = rng.normal(0, 0.5, size=2)
            for _ in range(per_object):
                rows.append((a, b) + offset + rng.normal(0, 1.0, size=2))
                labels.append(c)
                objects.append(len(objects) // per_object)
    rows = np.asarray(rows, dtype=np.float32)
    batch = circle_batch(np.full(len(rows), 30.0), probes=4, grid=(2, 2), seed=seed, labels=labels)
    frames = np.zeros_like(batch.frames)
    frames[:, :, 0, 0] = rows[:, :1]
    frames[:, :, 1, 1] = rows[:, 1:]
    n_objects = objects[-1] + 1
    return dataclasses.replace(
        batch, frames=frames, object_ids=np.asarray(objects),
        object_names=tuple(f"o{seed}-{k}" for k in range(n_objects)),
        class_names=tuple(class_names or (f"c{k}" for k in range(len(centres)))))


KNOWN = [(10.0, 10.0), (20.0, 20.0), (30.0, 30.0), (40.0, 40.0)]
OPTIONS = {"class_folds": 2, "max_touches": 3, "score": "class_distance"}


@pytest.fixture(scope="module")
def pair():
    train = two_taxel_batch(KNOWN, seed=1)
    return [calibrate(TaxelClassifier(taxel), train, **OPTIONS) for taxel in (0, 3)]


class Stub:
    """Only what the joint decision's choice and threshold read: classes and a calibration with the folds' scores
    (one K) of two scores."""

    classes_ = np.array(["a", "b"], dtype=object)

    def __init__(self, known, unknown=None, keep=0.5, digest="0" * 64):
        known = {n: [np.asarray(v, dtype=np.float64)] for n, v in
                 (known if isinstance(known, dict) else {"class_distance": known}).items()}
        unknown = {n: [np.asarray(v, dtype=np.float64)] for n, v in (unknown or {n: [0.0] for n in known}).items()}
        self.calibration_ = {"fold_known": known, "fold_unknown": unknown, "fold_groups": digest, "keep": keep,
                             "thresholds": np.zeros(1)}


def test_conformal_log_p_hand_computed():
    # (1 + how many known scores are <= s) / (3 + 1); below the smallest known score, one unit of log less per
    # standard deviation of the known scores (1, 2, 3: sqrt(2 / 3)) further down
    expected = np.log([0.5, 0.75, 1.0, 0.25]) - np.array([0.0, 0.0, 0.0, 3.0 / np.sqrt(2 / 3)])
    np.testing.assert_allclose(conformal_log_p([3.0, 1.0, 2.0], [1.0, 2.0, 5.0, -2.0]), expected)
    assert np.isfinite(conformal_log_p([1.0, 1.0], [-1e300]))  # no spread, far below: very low but finite


def test_joint_threshold_hand_computed():
    """Leave-one-out p-values: model a's known scores 1, 2, 3, 4 give 1/4, 2/4, 3/4, 1; model b's (the same groups)
    4, 3, 2, 1 give 1, 3/4, 2/4, 1/4. Sums of logs: log 1/4, log 3/8, log 3/8, log 1/4; keeping half of the groups
    means the threshold log 3/8 (two of the four at or above it)."""
    models = [Stub([1, 2, 3, 4]), Stub([4, 3, 2, 1])]
    assert joint_threshold(models, 1) == pytest.approx(np.log(3 / 8))
    assert joint_threshold(models, 5) == pytest.approx(np.log(3 / 8))  # a larger K uses the last K's scores


def test_joint_scores_hand_computed():
    """Both models kept two scores with the known fold scores 1, 2, 3, 4 (leave-one-out p-values 1/4 .. 1). The
    folds' unknown groups score 1.5 (p = 2/5) by class_distance and 10 (p = 1) by probability. Joint statistics of
    the known groups: 2 log(1/4, 2/4, 3/4, 1) = -2.77, -1.39, -0.58, 0. Unknown: class_distance twice 2 log 0.4 =
    -1.83, AUROC 3/4; one of each log 0.4 = -0.92, AUROC 1/2; probability twice 0, AUROC 1/8 (a tie counts half):
    class_distance for both."""
    known = {"probability": [1, 2, 3, 4], "class_distance": [1, 2, 3, 4]}
    unknown = {"probability": [10, 10], "class_distance": [1.5, 1.5]}
    assert joint_scores([Stub(known, unknown), Stub(known, unknown)]) == ("class_distance", "class_distance")
    flipped = {"probability": [1.5, 1.5], "class_distance": [10, 10]}
    assert joint_scores([Stub(known, unknown), Stub(known, flipped)]) == ("class_distance", "probability")


def test_each_model_misses_the_cluster_its_taxel_cannot_see_and_together_they_reject_both(pair):
    """Far cluster A reads (200, 20): taxel 0 sees it far off, taxel 3 sees class c1. Far cluster B reads
    (20, 200): the other way round. Each model alone keeps one cluster as c1; the joint rule rejects both and keeps
    the known classes' new objects about as often as each model alone."""
    by_taxel0, by_taxel3 = pair
    far_a = two_taxel_batch([(200.0, 20.0)], objects_per_class=5, seed=8, class_names=["c0"])
    far_b = two_taxel_batch([(20.0, 200.0)], objects_per_class=5, seed=9, class_names=["c0"])
    known = two_taxel_batch(KNOWN, objects_per_class=10, seed=7)
    groups = {name: np.arange(len(b)).reshape(-1, 3) for name, b in (("a", far_a), ("b", far_b), ("k", known))}

    def unknown_share(decision):
        return float(np.mean(decision["label"] == UNKNOWN))

    assert unknown_share(decide(by_taxel0, far_a, groups["a"])) == 1.0
    # a cluster a model sees among known readings is rejected about as often as known objects are (5 % asked)
    assert unknown_share(decide(by_taxel0, far_b, groups["b"])) <= 0.2
    assert (decide(by_taxel0, far_b, groups["b"])["closest"] == "c1").all()
    assert unknown_share(decide(by_taxel3, far_a, groups["a"])) <= 0.2
    assert unknown_share(decide(by_taxel3, far_b, groups["b"])) == 1.0
    for batch, g in ((far_a, groups["a"]), (far_b, groups["b"])):
        joint = joint_decide(pair, batch, g)
        assert (joint["label"] == UNKNOWN).all()
        # the far model's p-value lies far below 1 / (fold scores + 1): below every known fold score, by many spreads
        assert (joint["log_p"].min(axis=1) < -20).all()
    joint = joint_decide(pair, known, groups["k"])
    kept = 1 - unknown_share(joint)
    assert kept >= 0.85
    names = np.asarray(known.class_names, dtype=object)[known.labels[groups["k"][:, 0]]]
    assert np.mean(joint["closest"] == names) > 0.95  # the first model names the class
    assert joint["threshold"] == joint_threshold(pair, 3)


def test_refuses_models_it_cannot_combine(pair):
    with pytest.raises(InvalidArgumentError, match="at least two"):
        joint_decide(pair[:1], two_taxel_batch(KNOWN, seed=3))
    other = calibrate(TaxelClassifier(3), two_taxel_batch(KNOWN, seed=2), **OPTIONS)  # other training objects
    with pytest.raises(InvalidArgumentError, match="same data"):
        joint_decide([pair[0], other], two_taxel_batch(KNOWN, seed=3))
    reseeded = calibrate(TaxelClassifier(3), two_taxel_batch(KNOWN, seed=1), random_state=5, **OPTIONS)
    with pytest.raises(InvalidArgumentError, match="same data"):
        joint_decide([pair[0], reseeded], two_taxel_batch(KNOWN, seed=3))
    closed = calibrate(TaxelClassifier(3), two_taxel_batch(KNOWN, seed=1), open_set=False)
    with pytest.raises(InvalidArgumentError, match="without the open-set folds"):
        joint_decide([pair[0], closed], two_taxel_batch(KNOWN, seed=3))
    with pytest.raises(NotFittedError):
        joint_decide([pair[0], TaxelClassifier(3).fit(two_taxel_batch(KNOWN, seed=1))], two_taxel_batch(KNOWN, seed=3))


def test_the_fold_scores_survive_the_model_file_and_damage_is_refused(pair, tmp_path):
    loaded = [load_model(m.save(tmp_path / f"m{i}.vtm")) for i, m in enumerate(pair)]
    batch = two_taxel_batch(KNOWN + [(200.0, 20.0)], seed=11)
    groups = np.arange(len(batch)).reshape(-1, 3)
    a, b = joint_decide(pair, batch, groups), joint_decide(loaded, batch, groups)
    assert np.array_equal(a["score"], b["score"]) and np.array_equal(a["label"], b["label"])
    saved = dict(pair[0].calibration_)
    known = saved["fold_known"]
    for change in ({"fold_known": {n: [np.array([np.nan])] * 3 for n in known}},
                   {"fold_known": {n: v[:2] for n, v in known.items()}},
                   {"fold_known": {n: v[:1] * 3 if n == "distance" else v for n, v in known.items()}},
                   {"fold_unknown": {**saved["fold_unknown"], "magic": known["distance"]}},
                   {"fold_known": [known["class_distance"]]}, {"fold_groups": "not a digest"}):
        try:
            pair[0].calibration_ = {**saved, **change}
            path = pair[0].save(tmp_path / "bad.vtm")
        finally:
            pair[0].calibration_ = saved
        with pytest.raises(ModelFileError, match="calibration"):
            load_model(path)


def test_recognize_asks_the_other_models_and_the_command_line_too(pair, tmp_path, capsys):
    """A box pressed by the 2 x 2 pad reads near 0 on both taxels: each model alone and the two together answer
    "unknown"; the joint answer's threshold is the joint one for K touches. ``--also`` passes the second model."""
    from fusion.cli import main
    from fusion.experiments.recognize import recognize
    from perception.shapes import make_object
    from tests.fusion.test_experiments import write_off

    box = make_object("box", 0)
    result = recognize(pair[0], box, touches=2, strategy="blind", others=[pair[1]])
    assert result.unknown and result.label == UNKNOWN and result.threshold == joint_threshold(pair, 2)
    alone = recognize(pair[0], box, touches=2, strategy="blind")
    assert alone.unknown and alone.threshold != result.threshold
    with pytest.raises(InvalidArgumentError, match="tempered"):
        recognize(pair[0], box, touches=2, strategy="blind", rule="log", others=[pair[1]])
    other = copy.copy(pair[1])
    other.n_probes_ = 7
    with pytest.raises(InvalidArgumentError, match="probe count"):
        recognize(pair[0], box, touches=2, strategy="blind", others=[other])
    paths = [m.save(tmp_path / f"m{i}.vtm") for i, m in enumerate(pair)]
    mesh = write_off(box, tmp_path / "box.off")
    assert main(["recognize", str(mesh), "--model", str(paths[0]), "--also", str(paths[1]), "--touches", "2",
                 "--strategy", "blind", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["unknown"] is True and out["also"] == [str(paths[1])]
    assert out["threshold"] == pytest.approx(joint_threshold(pair, 2), abs=1e-6)
    assert main(["recognize", str(mesh), "--model", str(paths[0]), "--also", str(tmp_path / "none.vtm")]) == 2
    assert "none.vtm: no model there" in capsys.readouterr().err


def test_the_camera_command_asks_the_other_models_too(pair, tmp_path, capsys):
    """A virtual capture of a box, touched twice with the toy models' 2 x 2 pad: the joint answer is "unknown" at
    the joint threshold; ``--also`` without ``--model`` is refused before any capture."""
    from fusion.cli import main

    paths = [m.save(tmp_path / f"m{i}.vtm") for i, m in enumerate(pair)]
    assert main(["camera", "--source", "virtual:box/1", "--views", "2", "--contours", "2", "--model", str(paths[0]),
                 "--also", str(paths[1]), "--json"]) == 0
    prediction = json.loads(capsys.readouterr().out)["prediction"]
    assert prediction["unknown"] is True and prediction["class"] == UNKNOWN
    assert prediction["threshold"] == pytest.approx(joint_threshold(pair, 2))
    assert main(["camera", "--source", "virtual:box/1", "--also", str(paths[1])]) == 2
    assert "give --model too" in capsys.readouterr().err


def test_the_first_model_names_the_class_when_they_disagree(pair):
    """Sequences reading (20, 30): the first model (taxel 0) says c1, the second (taxel 3) c2; joint_decide answers
    the first's class, in either order."""
    batch = two_taxel_batch([(20.0, 30.0)], objects_per_class=2, seed=12, class_names=["c0"])
    groups = np.arange(len(batch)).reshape(-1, 3)
    assert (decide(pair[0], batch, groups)["closest"] == "c1").all()
    assert (decide(pair[1], batch, groups)["closest"] == "c2").all()
    assert (joint_decide(pair, batch, groups)["closest"] == "c1").all()
    assert (joint_decide(pair[::-1], batch, groups)["closest"] == "c2").all()


@pytest.mark.parametrize("change", ["classes", "keep", "scores", "twice"])
def test_refuses_models_calibrated_otherwise(pair, change):
    """Same training objects and folds (the digest matches), but other class names, another keep, fold scores of
    other lengths, or one model given twice: refused, naming the problem."""
    train = two_taxel_batch(KNOWN, seed=1)
    if change == "classes":
        other = calibrate(TaxelClassifier(3), dataclasses.replace(train, class_names=("d0", "d1", "d2", "d3")),
                          **OPTIONS)
        assert other.calibration_["fold_groups"] == pair[0].calibration_["fold_groups"]
    elif change == "keep":
        other = calibrate(TaxelClassifier(3), train, keep=0.9, **OPTIONS)
    elif change == "scores":
        other = copy.deepcopy(pair[1])
        other.calibration_["fold_known"] = {n: [a[:-1] for a in v] for n, v in other.calibration_["fold_known"].items()}
    else:
        other = pair[0]
    with pytest.raises(InvalidArgumentError, match="twice" if change == "twice" else "same data"):
        joint_decide([pair[0], other], train)


def test_refuses_hostile_arguments(pair):
    batch = two_taxel_batch(KNOWN, seed=3)
    for models in (pair[0], None, "ab", {"a": pair[0], "b": pair[1]}):
        with pytest.raises(InvalidArgumentError, match="list of calibrated models"):
            joint_decide(models, batch)
    for k in (0, -1, 1.5, True, "3", None):
        with pytest.raises(InvalidArgumentError, match="positive integer"):
            joint_threshold(pair, k)
    for groups in ([["a"]], [[np.nan]], [[2**70]], [[0.5, 1.2]], [[True]]):
        with pytest.raises(InvalidArgumentError, match="integer index array"):
            joint_decide(pair, batch, groups)
    with pytest.raises(InvalidArgumentError, match="one \\(G,\\) score array per model"):
        joint_log_p(pair, [{"distance": np.zeros(3)}, {"distance": np.zeros(4)}], 1, ("distance", "distance"))
    with pytest.raises(InvalidArgumentError, match="a mapping with its score"):
        joint_log_p(pair, [np.zeros(3), np.zeros(3)], 1)
    with pytest.raises(InvalidArgumentError, match="kept score"):
        joint_threshold(pair, 1, ("magic", "distance"))
    for known, scores in (([], [0.0]), ([1.0, np.nan], [0.0]), ([1.0], [np.inf]), ([1.7e308, -1.7e308], [0.0])):
        with pytest.raises(DatasetError):
            conformal_log_p(known, scores)
    from fusion.experiments.recognize import recognize
    from perception.shapes import make_object

    box = make_object("box", 0)
    for others, error in ((None, InvalidArgumentError), (pair[1], InvalidArgumentError),
                          (["x"], InvalidArgumentError), ([TaxelClassifier(3)], NotFittedError)):
        with pytest.raises(error):
            recognize(pair[0], box, touches=2, strategy="blind", others=others)


def test_a_model_file_with_fold_scores_but_no_thresholds_or_extreme_scores_is_refused(pair, tmp_path):
    saved = dict(pair[1].calibration_)
    for change in ({"thresholds": None, "score": None},
                   {"fold_known": {n: [np.full(len(a), 1.7e308) for a in v] for n, v in saved["fold_known"].items()}},
                   {"fold_groups": "0" * 63}):
        try:
            pair[1].calibration_ = {k: v for k, v in {**saved, **change}.items() if v is not None}
            path = pair[1].save(tmp_path / "bad.vtm")
        finally:
            pair[1].calibration_ = saved
        with pytest.raises(ModelFileError, match="calibration"):
            load_model(path)


def test_recognize_file_refuses_a_bare_path_and_a_file_given_twice(pair, tmp_path):
    from fusion.experiments.recognize import recognize_file
    from perception.shapes import make_object
    from tests.fusion.test_experiments import write_off

    paths = [m.save(tmp_path / f"m{i}.vtm") for i, m in enumerate(pair)]
    mesh = write_off(make_object("box", 0), tmp_path / "box.off")
    with pytest.raises(InvalidArgumentError, match="list of model files"):
        recognize_file(mesh, paths[0], others=str(paths[1]))
    with pytest.raises(InvalidArgumentError, match="twice"):
        recognize_file(mesh, paths[0], others=(tmp_path / "." / "m0.vtm",))


def test_a_set_distance_chosen_for_the_joint_decision_is_computed_even_where_the_model_chose_another(pair,
                                                                                                    monkeypatch):
    """Both models chose class_distance alone; if the joint choice reads their set distance, joint_decide computes
    it (the distances to each training object) and scores as the experiment's per-touch path does."""
    from fusion import openset
    from fusion.openset import group_scores, per_touch

    monkeypatch.setattr(openset, "joint_scores", lambda models: ("set_distance", "set_distance"))
    batch = two_taxel_batch(KNOWN + [(200.0, 20.0)], seed=13)
    groups = np.arange(len(batch)).reshape(-1, 3)
    joint = joint_decide(pair, batch, groups)
    assert joint["scores"] == ("set_distance", "set_distance")
    expected = 0.0
    for m in pair:
        proba, distances, by_object = per_touch(m, batch)
        set_distance = group_scores(proba, groups, m.calibration_, distances, by_object)["set_distance"]
        expected = expected + conformal_log_p(m.calibration_["fold_known"]["set_distance"][2], set_distance)
    np.testing.assert_allclose(joint["score"], expected)
