"""Replaying next-touch criteria over a candidate bank: the information criterion's replay is the episode that
run_episode runs with the information policy (the same planes, posteriors to the bit, misses included), a criterion
sees no untouched plane's real reading, the deciding classifier does not choose, and bad input is refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.active import InformationPolicy, make_policy, noisy_copy, run_episode
from fusion.active.replay import build_bank, information_criterion, replay
from fusion.decide import fuse_touches
from perception.errors import InvalidArgumentError
from perception.shapes import make_object
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
    from fusion.active.replay import CandidateBank
    from tactile.contours import Plane

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
