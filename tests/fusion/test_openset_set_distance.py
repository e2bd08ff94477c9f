"""The open-set set distance (how well K touches together fit one training object): hand-computed values through
``group_scores`` and ``decide`` after a model-file round trip, the fold's distances to its training objects, "auto"
choosing it where only it tells chimeras, and model files whose reference objects are refused or bounded."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.base import load_model
from fusion.openset import DISTANCE_FLOOR, _Inner, calibrate, class_distances, decide, group_scores
from perception.errors import DatasetError, InvalidArgumentError, ModelFileError
from tests.fusion._synthetic import circle_batch
from tests.fusion.test_openset import KNOWN, MeanClassifier, toy_batch


def batch_of(values, labels, objects, n_classes, seed=0):
    """Sequences whose every frame reads ``values[i]``: MeanClassifier's raw feature is exactly that value."""
    batch = circle_batch(np.full(len(values), 30.0), probes=4, grid=(2, 2), seed=seed, labels=list(labels))
    frames = np.broadcast_to(np.asarray(values, np.float32)[:, None, None, None], batch.frames.shape).copy()
    n = int(max(objects)) + 1
    return dataclasses.replace(batch, frames=frames, object_ids=np.asarray(objects),
                               object_names=tuple(f"s{seed}-{k:03d}" for k in range(n)),
                               class_names=tuple(f"c{k}" for k in range(n_classes)))


class RawEmbed(MeanClassifier):
    """MeanClassifier whose feature space is the raw mean reading (not divided by a fitted scale)."""

    def embed(self, batch):
        return self._x(batch)[:, None]


class NoSpace(MeanClassifier):
    embed = None  # no feature space


# ---- a hand-computed example: neighbors = 2, 1-D features
# objects: A (class 0) at 0, 2; B (class 0) at 10, 14; C (class 1) at 30, 31, 35; D (class 1) a single point at 50
REF = np.array([0.0, 2.0, 10.0, 14.0, 30.0, 31.0, 35.0, 50.0])[:, None]
LABELS = np.array([0, 0, 0, 0, 1, 1, 1, 1])
OWNERS = np.array([0, 0, 1, 1, 2, 2, 2, 3])
TOUCHES = np.array([1.0, 12.0, 31.0, 50.0])  # t0 .. t3
# d(touch, object) = mean distance to the object's 2 nearest points (1 for D):
#   t0: A 1, B 11, C 29.5, D 49;  t1: A 11, B 2, C 18.5, D 38;  t2: A 30, B 19, C 0.5, D 19;  t3: A 49, B 38, C 17, D 0 (floored)
GROUPS = np.array([[0, 1], [0, 0], [1, 1], [2, 2], [3, 3], [0, 2]])
EXPECTED = np.array([
    -np.log(11) / 2,                 # t0, t1: A (log 1 + log 11) / 2 beats B (log 11 + log 2) / 2
    0.0,                             # t0 alone: A, log 1
    -np.log(2),                      # t1: B
    np.log(2),                       # t2: C, -log 0.5 (C is the largest-numbered object but one)
    -np.log(DISTANCE_FLOOR),         # t3: exactly on D's single point: the floor, finite
    -min((np.log(1) + np.log(30)) / 2, (np.log(29.5) + np.log(0.5)) / 2),  # t0, t2: A or C
])


def test_set_distance_known_answer_from_hand_built_embeddings():
    """By hand (the comments above); a touch exactly on a one-sequence object scores the floor, not +inf."""
    by_object = class_distances(TOUCHES[:, None], REF, OWNERS, 4, neighbors=2)
    np.testing.assert_allclose(by_object[:, :2], [[1, 11], [11, 2], [30, 19], [49, 38]])
    s = group_scores(np.full((4, 2), 0.5), GROUPS, {"dependence": 0.0}, None, by_object)
    assert np.isfinite(s["set_distance"]).all()
    np.testing.assert_allclose(s["set_distance"], EXPECTED, rtol=1e-12)
    # the class distance of t0, t1 fits class 0 (A for t0, B for t1): the set distance is lower (a chimera)
    by_class = class_distances(TOUCHES[:, None], REF, LABELS, 2, neighbors=2)
    assert group_scores(np.full((4, 2), 0.5), GROUPS[:1], {"dependence": 0.0}, by_class)["distance"][0] == \
        pytest.approx(-np.log(2) / 2)


def _hand_model():
    model = RawEmbed().fit(batch_of([0.0, 2.0, 30.0, 31.0], [0, 0, 1, 1], [0, 0, 1, 1], 2))
    model.calibration_ = {"temperature": 1.0, "smoothing": 0.0, "dependence": 0.0, "keep": 0.95, "neighbors": 2,
                          "max_touches": 2, "score": "set_distance", "thresholds": np.array([0.0, 0.0]),
                          "inner_auroc": {}, "reference": REF.copy(), "reference_labels": LABELS.copy(),
                          "reference_objects": OWNERS.copy()}
    return model


def test_decide_with_set_distance_known_answer_after_a_round_trip(tmp_path):
    """decide (per_touch -> group_scores) of a hand-calibrated set-distance model, saved and loaded: every
    object counted (the last one too), by its reference objects, over the whole reference."""
    model = load_model(_hand_model().save(tmp_path / "hand.vtm"))
    touches = batch_of(TOUCHES, [0] * 4, [0, 1, 2, 3], 2, seed=5)
    np.testing.assert_allclose(decide(model, touches, GROUPS)["score"], EXPECTED, rtol=1e-12)
    assert model.known_score(touches, GROUPS[:1])[0] == pytest.approx(-np.log(11) / 2)


@pytest.mark.parametrize("change, refused", [
    ({"reference_objects": None}, True),                        # set_distance needs them (older file + new score)
    ({"reference_objects": np.r_[OWNERS[:-1], 8]}, True),      # an id == the number of reference rows
    ({"reference_objects": np.r_[OWNERS[:-1], 7]}, False),     # the largest id possible: loads
    ({"reference_objects": OWNERS.astype(np.uint8)}, True),
    ({"reference_objects": OWNERS.astype(bool)}, True),
])
def test_reference_objects_bounds_in_a_model_file(tmp_path, change, refused):
    """The set distance needs reference objects (a file without them once loaded, then raised KeyError), ids
    below the reference's rows, signed integers."""
    model = _hand_model()
    model.calibration_ = {k: v for k, v in {**model.calibration_, **change}.items() if v is not None}
    path = model.save(tmp_path / "m.vtm")
    if refused:
        with pytest.raises(ModelFileError, match="m.vtm.*reference objects"):
            load_model(path)
    else:
        scores = decide(load_model(path), batch_of(TOUCHES, [0] * 4, [0, 1, 2, 3], 2), GROUPS)["score"]
        assert np.isfinite(scores).all()


def test_set_distance_needs_a_feature_space():
    """Refused up front (it once failed inside the folds with an IndexError)."""
    with pytest.raises(InvalidArgumentError, match="feature space"):
        calibrate(NoSpace(), toy_batch(KNOWN, seed=1), class_folds=2, max_touches=2, score="set_distance")


def test_a_set_distance_calibration_has_thresholds_and_its_folds_scores():
    """Asked for by name: the leave-classes-out folds score it (their objects given) and fit its thresholds."""
    model = calibrate(MeanClassifier(), toy_batch(KNOWN, seed=1), class_folds=2, max_touches=3,
                      score="set_distance")
    cal = model.calibration_
    assert cal["score"] == "set_distance" and np.isfinite(cal["thresholds"]).all()
    assert all(a is not None for a in cal["inner_auroc"]["set_distance"])


def test_fold_object_distances_are_to_the_training_objects():
    """_Inner.run's (T, O) distances: one column per training object (numbered as np.unique numbers them), each
    the mean distance to that object's nearest sequences (an independent class_distances call on the raw
    features)."""
    batch = toy_batch(KNOWN, seed=1)
    y = np.asarray(batch.labels)
    objects = np.asarray(batch.object_ids)
    train, test = np.flatnonzero(objects % 3 != 0), np.flatnonzero(objects % 3 == 0)
    inner = _Inner(RawEmbed(), batch, y, np.array([f"c{k}" for k in range(4)], dtype=object), 2)
    *_, by_object = inner.run(train, test, want_distances=True, objects=objects)
    x = batch.frames.astype(np.float64).mean(axis=(1, 2, 3))[:, None]
    _, owner = np.unique(objects[train], return_inverse=True)
    expected = class_distances(x[test], x[train], owner, len(np.unique(objects[train])), 2)
    assert by_object.shape == (len(test), len(np.unique(objects[train])))
    np.testing.assert_allclose(by_object, expected)


def chimera_batch(objects_per_class=10, per_object=6, noise=0.2, seed=0):
    """c0: objects touched all at 0 or all at 10 (alternately); c1: every object touched half at 0, half at 10 (a
    chimera of two c0 objects); c2: at 40. With c1 left out, its objects fit class c0 touch by touch (distance and
    class distance cannot tell), but no single c0 object: only the set distance tells."""
    rng = np.random.default_rng(seed)
    values, labels, objects = [], [], []
    for o in range(3 * objects_per_class):
        c, j = divmod(o, objects_per_class)
        for t in range(per_object):
            centre = (0.0, 10.0)[j % 2] if c == 0 else (0.0, 10.0)[t % 2] if c == 1 else 40.0
            values.append(centre + rng.normal(0, noise))
            labels.append(c)
            objects.append(o)
    return batch_of(values, labels, objects, 3, seed)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_auto_chooses_the_set_distance_where_it_tells_chimeras(seed):
    """Mean inner AUROC over K = 1..4, seeds 0-5: set distance 0.84-0.87, distance 0.73-0.80, class distance
    0.71-0.78."""
    model = calibrate(MeanClassifier(), chimera_batch(seed=seed), class_folds=3, max_touches=4, neighbors=2,
                      random_state=seed)
    aurocs = {k: np.mean(v) for k, v in model.calibration_["inner_auroc"].items()}
    assert model.calibration_["score"] == "set_distance"
    assert aurocs["set_distance"] >= max(aurocs["distance"], aurocs["class_distance"]) + 0.03


def test_many_objects_with_rows_in_any_order_match_a_brute_force_computation():
    """3,000 objects of 1-3 rows each, the rows shuffled (the groups are found by sorting once): each touch's mean
    distance to an object's 2 nearest rows, computed here from the full distance matrix."""
    rng = np.random.default_rng(4)
    owners = rng.permutation(np.repeat(np.arange(3000), rng.integers(1, 4, 3000)))
    ref = rng.normal(size=(len(owners), 3))
    touches = rng.normal(size=(5, 3))
    got = class_distances(touches, ref, owners, 3000, neighbors=2)
    d = np.linalg.norm(touches[:, None] - ref[None], axis=2)
    for o in rng.choice(3000, 50, replace=False):
        nearest = np.sort(d[:, owners == o], axis=1)[:, :2]
        np.testing.assert_allclose(got[:, o], nearest.mean(axis=1), rtol=1e-12)


def test_reference_objects_are_checked_whatever_the_score(tmp_path):
    """A calibration without the open-set folds (no score) holding reference objects: checked all the same (a
    huge id once loaded and made per_touch allocate hundreds of TiB)."""
    model = _hand_model()
    model.calibration_ = {k: v for k, v in model.calibration_.items() if k not in ("score", "thresholds")}
    model.calibration_["reference_objects"] = np.full(len(REF), 10**12)
    with pytest.raises(ModelFileError, match="reference objects"):
        load_model(model.save(tmp_path / "no-score.vtm"))


def test_class_distances_refuse_labels_out_of_range_and_results_above_the_memory_limit(monkeypatch):
    with pytest.raises(DatasetError, match="labels must be integers in 0..1"):
        class_distances(TOUCHES[:, None], REF, np.full(len(REF), 2), 2)
    monkeypatch.setenv("VISUOTACTILE_MAX_MEMORY_MB", "1")
    with pytest.raises(DatasetError, match="above the limit"):
        class_distances(np.zeros((100_000, 1)), REF, OWNERS, 4)
