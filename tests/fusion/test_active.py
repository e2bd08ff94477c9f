"""Next-touch policies and sequential decisions: the information gain against hand-computed values, the planning
contract (a policy never depends on the true object, only on the visual model and the outcomes so far), the
information policy following the posterior, the stopping rule, determinism and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.active import (
    ActiveState,
    InformationPolicy,
    information_gain,
    make_policy,
    noisy_copy,
    plan_scores,
    run_episode,
    same_plane,
    smoothed,
    stopped,
    visual_belief,
)
from perception.errors import InvalidArgumentError
from perception.shapes import make_object
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor
from tactile.touching import touch

CLASSES = np.array(["a", "b", "c"], dtype=object)


class ConstantClassifier:
    """A fitted-classifier stand-in whose output is the same for every sequence."""

    classes_ = CLASSES
    probes = 8

    def __init__(self, proba=(0.9, 0.05, 0.05)):
        self.proba = np.asarray(proba, dtype=np.float64)

    def sensor(self):
        return FSRSensor(rows=8, cols=8)

    def predict_proba(self, batch):
        return np.tile(self.proba, (len(batch), 1))


class OrientationClassifier(ConstantClassifier):
    """Reads a contour plane's orientation: planes within 45 degrees of horizontal say "a" confidently, the others
    are torn between "b" and "c"."""

    CONFIDENT, TORN = (0.8, 0.1, 0.1), (0.1, 0.45, 0.45)

    def predict_proba(self, batch):
        flat = np.abs(batch.plane_normals[:, 2]) > np.sqrt(0.5)
        return np.where(flat[:, None], self.CONFIDENT, self.TORN)


@pytest.fixture(scope="module")
def objects():
    mug, box = make_object("mug", 0), make_object("box", 0)
    return mug, box, noisy_copy(mug, 0.5, seed=1)


class TestInformationGain:
    def test_hand_computed(self):
        # p uniform, q = (0.8, 0.2): the new posterior is q, KL(q || p) = 0.8 ln 1.6 + 0.2 ln 0.4.
        assert information_gain([0.5, 0.5], [0.8, 0.2]) == pytest.approx(0.8 * np.log(1.6) + 0.2 * np.log(0.4))
        # p = (0.9, 0.1), q = (0.1, 0.9): the new posterior is (0.5, 0.5).
        assert information_gain([0.9, 0.1], [0.1, 0.9]) == pytest.approx(0.5 * np.log(0.5 / 0.9) + 0.5 * np.log(5))
        assert information_gain([0.2, 0.3, 0.5], [1 / 3] * 3) == pytest.approx(0.0, abs=1e-15)

    def test_batched_finite_and_non_negative(self):
        rng = np.random.default_rng(0)
        outcomes = rng.dirichlet(np.ones(4), size=(5, 3))
        outcomes[0, 0] = [1.0, 0.0, 0.0, 0.0]  # a zero probability stays finite
        gain = information_gain([0.0, 0.5, 0.25, 0.25], outcomes)
        assert gain.shape == (5, 3) and np.isfinite(gain).all() and (gain >= 0).all()

    @pytest.mark.parametrize("posterior, outcomes", [([0.5, 0.5], [0.2, 0.3, 0.5]), ([0.5, np.nan], [0.5, 0.5]),
                                                     ([0.5, 0.5], [-0.1, 1.1])])
    def test_bad_input(self, posterior, outcomes):
        with pytest.raises(InvalidArgumentError):
            information_gain(posterior, outcomes)


class TestContract:
    @pytest.mark.parametrize("name", ["random", "saliency", "information"])
    def test_plans_do_not_depend_on_the_true_object(self, objects, name):
        """Same visual model and same touch outcomes (a classifier whose output never changes) -> the same planes,
        whichever object is really touched."""
        mug, box, visual = objects
        clf, policy = ConstantClassifier(), make_policy(name, 3)
        runs = [run_episode(true, visual, clf, policy, max_touches=3, seed=0) for true in (mug, box)]
        assert all(same_plane(a, b) for a, b in zip(runs[0].planes, runs[1].planes))
        assert len({tuple(np.round(p.normal, 9)) for p in runs[0].planes}) == 3  # three distinct contours

    def test_first_choice_depends_on_the_visual_model_only(self, objects):
        mug, box, visual = objects
        clf = OrientationClassifier()  # outcomes differ between the objects, the first plan must not
        first = [run_episode(true, visual, clf, make_policy("information", 0), max_touches=1).planes[0]
                 for true in (mug, box)]
        assert same_plane(*first)
        assert np.allclose(first[0].point, visual.center)  # through the visual model's centre

    def test_information_choice_follows_the_posterior(self, objects):
        """Touches so far sure of "a": the candidate that confirms "a" (a flat plane reads it at 0.8) scores best;
        sure of "b": the torn candidate, which moves the decision towards "b" (0.45) and away from "a"."""
        _, _, visual = objects
        clf = OrientationClassifier()
        policy = InformationPolicy(0, candidates=24, variants=1)
        state = ActiveState(visual, clf)
        planes, _ = policy.simulated(state)
        flat = np.array([abs(p.normal[2]) > np.sqrt(0.5) for p in planes])
        assert flat.any() and (~flat).any()  # both kinds of candidate exist
        sure_a = ActiveState(visual, clf, planes=[planes[-1]], probabilities=[np.array([0.98, 0.01, 0.01])])
        sure_b = ActiveState(visual, clf, planes=[planes[-1]], probabilities=[np.array([0.01, 0.98, 0.01])])
        assert abs(policy.propose(sure_a).normal[2]) > np.sqrt(0.5)
        assert abs(policy.propose(sure_b).normal[2]) <= np.sqrt(0.5)


class FrameClassifier(ConstantClassifier):
    """Reads the frames: each sequence's mean gap (mm) decides between "a" and "b", so any change of a frame shows."""

    def predict_proba(self, batch):
        logit = batch.frames.reshape(len(batch), -1).mean(axis=1).astype(np.float64)
        e = np.exp(np.stack([logit, -logit, np.zeros_like(logit)], axis=1))
        return e / e.sum(axis=1, keepdims=True)


def test_simulated_outcomes_are_those_of_touching_each_variant(objects):
    """The candidates' outcomes (M, variants, C) are the classifier's answers to touch() on the smoothed visual
    model, variant v seeded with seed + v and jittered from the second on: the planes cut once and the variants
    pressed together give exactly what touching variant by variant gives."""
    _, _, visual = objects
    clf = FrameClassifier()
    policy = InformationPolicy(5, candidates=6, variants=3, jitter_mm=0.7)
    planes, outcomes = policy.simulated(ActiveState(visual, clf))
    assert outcomes.shape == (len(planes), 3, 3)
    surface = smoothed(visual, policy.smooth_iterations)
    for v in range(3):
        sequences = touch(surface, "blind", len(planes), clf.sensor(), clf.probes, seed=5 + v, planes=planes,
                          jitter_mm=0.7 if v else 0.0)
        batch = SequenceBatch.from_sequences(sequences, class_names=list(CLASSES), sensor_spec=clf.sensor().spec())
        np.testing.assert_array_equal(outcomes[:, v], clf.predict_proba(batch))
    assert not np.array_equal(outcomes[:, 0], outcomes[:, 1])  # the jittered variant reads other frames


def test_same_as_any_is_same_plane_for_each():
    """The vectorised test the information policy draws its candidates with answers as same_plane does, plane by
    plane: equal planes, flipped normals, points and normals a hair apart on either side of the tolerances."""
    from fusion.active.policies import _same_as_any
    from tactile.contours import Plane

    rng = np.random.default_rng(0)
    base = [Plane(rng.normal(size=3) * 50, n / np.linalg.norm(n)) for n in rng.normal(size=(4, 3))]
    others = []
    for p in base:
        others += [p, Plane(p.point, -p.normal), Plane(p.point + 1e-10, p.normal), Plane(p.point + 1e-3, p.normal),
                   Plane(p.point * (1 + 2e-6), p.normal)]
        for tilt in (1e-7, 1e-5):  # 1 - cos: about 5e-15 (the same plane) and 5e-11 (another)
            normal = p.normal + np.array([tilt, 0.0, 0.0])
            others.append(Plane(p.point, normal / np.linalg.norm(normal)))
    points = np.array([o.point for o in others])
    normals = np.array([o.normal for o in others])
    for p in base + others:
        expected = [same_plane(p, o) for o in others]
        assert _same_as_any(p, points, normals).tolist() == expected
    assert 0 < sum(same_plane(base[0], o) for o in others) < len(others)  # both answers occur


def test_same_as_any_at_the_tolerances():
    """At np.allclose's bounds exactly, and where its relative tolerance (taken on the second plane's point) decides
    by itself: a point 1e-9 mm from the origin is 'close' to it (|a - b| <= atol), and 100 mm against
    100 - 9.99995e-4 mm is close one way round only."""
    from fusion.active.policies import _same_as_any
    from tactile.contours import Plane

    normal = np.array([0.0, 0.6, 0.8])
    pairs = [(Plane(np.array([1e-9, 0.0, 0.0]), normal), Plane(np.zeros(3), normal)),
             (Plane(np.array([100.0 - 9.99995e-4, 5.0, 0.0]), normal), Plane(np.array([100.0, 5.0, 0.0]), normal))]
    answers = []
    for a, b in pairs:
        for p, q in ((a, b), (b, a)):
            expected = same_plane(p, q)
            assert _same_as_any(p, q.point[None], q.normal[None]).tolist() == [expected]
            answers.append(expected)
    assert answers == [True, True, True, False]  # the cases are at the bounds: both answers occur


def test_candidates_are_the_distinct_planes_in_the_order_drawn():
    """A box of 8 vertices cut through its centre gives few planes, drawn again and again: the candidates are the
    first draws that are not same_plane as one kept before (the one just kept included), in the order drawn."""
    import open3d as o3d

    from perception.geometry import ObjectModel
    from tactile.touching import Toucher

    mesh = o3d.geometry.TriangleMesh.create_box(60.0, 40.0, 50.0)
    cube = ObjectModel(np.asarray(mesh.vertices) - [30.0, 20.0, 25.0], np.asarray(mesh.triangles), name="cube")
    policy = InformationPolicy(0, candidates=5, variants=1)
    state = ActiveState(cube, ConstantClassifier())
    planes, _ = policy.simulated(state)
    rng = policy._rng(policy._entry(state), 2**31)  # the draws of the candidates, replayed on a Toucher of our own
    toucher, kept, again, just_kept = Toucher(cube, "blind", probes=state.probes), [], 0, 0
    while len(kept) < 5:
        plane = toucher.draw(rng).plane
        if any(same_plane(plane, k) for k in kept):
            again, just_kept = again + 1, just_kept + same_plane(plane, kept[-1])
        else:
            kept.append(plane)
    assert again > 0 and just_kept > 0  # planes were drawn again, some just after being kept
    assert len(planes) == 5 and all(same_plane(p, k) for p, k in zip(planes, kept))
    assert not any(same_plane(p, q) for i, p in enumerate(planes) for q in planes[i + 1:])


class TestPlanScores:
    def test_hand_computed(self):
        # Nothing touched, visual weight 1: belief = the normalised geometric mean of the candidates' outcomes;
        # each candidate's score is belief . q (the decision after one touch is its outcome).
        q = np.array([[[0.8, 0.2]], [[0.4, 0.6]]])
        g = np.sqrt(q[0, 0] * q[1, 0])
        belief = g / g.sum()
        assert visual_belief([], q) == pytest.approx(belief)
        assert plan_scores(np.zeros((0, 2)), q) == pytest.approx([belief @ q[0, 0], belief @ q[1, 0]])
        # Visual weight 0 and one touch (0.5, 0.5): belief uniform, every decision sums to 1: 0.5 each.
        assert plan_scores([[0.5, 0.5]], q, visual_weight=0.0) == pytest.approx([0.5, 0.5])
        # One touch (0.9, 0.1), weight 0: belief (0.9, 0.1); after candidate 0 the decision is (0.72, 0.02) / 0.74.
        assert plan_scores([[0.9, 0.1]], q, visual_weight=0.0)[0] == pytest.approx((0.9 * 0.72 + 0.1 * 0.02) / 0.74)
        assert plan_scores(np.zeros((0, 2)), q, [True, False])[0] == -np.inf

    def test_touches_that_contradict_the_camera_turn_the_belief(self):
        q = np.array([[[0.7, 0.3]], [[0.6, 0.4]]])  # the camera's view leans to class 0
        assert visual_belief([], q)[0] > 0.5
        assert visual_belief([[0.05, 0.95]], q)[1] > 0.9

    @pytest.mark.parametrize("probabilities, outcomes", [([], np.ones((2, 3))), ([[0.5, 0.5]], np.ones((2, 1, 3))),
                                                         ([], np.full((2, 1, 2), np.nan))])
    def test_bad_input(self, probabilities, outcomes):
        with pytest.raises(InvalidArgumentError):
            plan_scores(probabilities, outcomes)


class TestEpisode:
    def test_stopping_rule(self, objects):
        mug, _, visual = objects
        clf = ConstantClassifier((0.9, 0.05, 0.05))
        # After one touch the posterior is (0.9, ...); after two 0.81 / (0.81 + 2 x 0.0025) = 0.99387.
        assert run_episode(mug, visual, clf, make_policy("random"), threshold=0.85).touches == 1
        episode = run_episode(mug, visual, clf, make_policy("random"), max_touches=5, threshold=0.99)
        assert episode.touches == 2 and episode.decision == "a"
        assert episode.posteriors[-1, 0] == pytest.approx(0.81 / 0.815)
        full = run_episode(mug, visual, clf, make_policy("random"), max_touches=5)
        assert full.touches == 5 and stopped(full, 0.99) == ("a", 2)
        assert full.step_seconds().shape == (5,) and (full.step_seconds() > 0).all()

    def test_same_seed_same_bytes(self, objects):
        mug, _, visual = objects
        clf = OrientationClassifier()
        a, b = (run_episode(mug, visual, clf, make_policy("information", 1), max_touches=3, seed=2) for _ in range(2))
        assert a.posteriors.tobytes() == b.posteriors.tobytes()
        assert all(p.normal.tobytes() == q.normal.tobytes() for p, q in zip(a.planes, b.planes))

    @pytest.mark.parametrize("kwargs", [{"max_touches": 0}, {"threshold": 1.5}, {"threshold": float("nan")},
                                        {"seed": -1}])
    def test_bad_settings(self, objects, kwargs):
        mug, _, visual = objects
        with pytest.raises(InvalidArgumentError):
            run_episode(mug, visual, ConstantClassifier(), make_policy("random"), **kwargs)

    @pytest.mark.parametrize("kwargs", [{"candidates": 10**6}, {"candidates": 50_001, "variants": 2}])
    def test_candidate_budget_within_the_contour_limit(self, kwargs):
        """A budget beyond the contour limit (100,000 simulated touches per visual model) is refused when the policy
        is made, not after drawing its planes."""
        with pytest.raises(InvalidArgumentError, match="above the limit"):
            InformationPolicy(0, **kwargs)
        assert InformationPolicy(0, candidates=50_000, variants=2).candidates == 50_000

    @pytest.mark.parametrize("label", ["jitter_mm", "visual_weight"])
    @pytest.mark.parametrize("value", ["1", 10**400, True, -0.5, float("nan"), None])
    def test_information_settings_that_are_no_numbers_are_refused_by_name(self, label, value):
        """A string or an integer beyond the float range raised numpy's TypeError from isfinite."""
        with pytest.raises(InvalidArgumentError, match=f"^information policy: {label} must be a finite number"):
            InformationPolicy(0, **{label: value})

    def test_jitter_beyond_a_metre_is_refused(self):
        with pytest.raises(InvalidArgumentError, match=r"jitter_mm must be a finite number in \[0, 1000\] mm"):
            InformationPolicy(0, jitter_mm=1e308)
        assert InformationPolicy(0, jitter_mm=1000).jitter_mm == 1000.0

    def test_bad_policies(self):
        with pytest.raises(InvalidArgumentError, match="unknown touch policy"):
            make_policy("greedy")
        with pytest.raises(InvalidArgumentError, match="candidates"):
            make_policy("information", candidates=0)
        with pytest.raises(InvalidArgumentError, match="visual_weight"):
            make_policy("information", visual_weight=-1.0)
        with pytest.raises(InvalidArgumentError, match="smooth_iterations"):
            make_policy("information", smooth_iterations=-1)
        with pytest.raises(InvalidArgumentError, match="the random policy takes cache_size; got candidates"):
            make_policy("random", candidates=3)
        with pytest.raises(InvalidArgumentError, match="the information policy takes candidates, .*; got foo"):
            make_policy("information", foo=1)  # a project error, not the TypeError of an unknown keyword
        with pytest.raises(InvalidArgumentError, match="unknown touch policy"):
            make_policy(["random"])
        with pytest.raises(InvalidArgumentError, match="unknown touch policy"):
            make_policy(np.array(["random"]))  # compares equal to "random", but is no name


class TestNoisyCopy:
    def test_noise_along_normals(self, objects):
        mug = objects[0]
        assert np.array_equal(noisy_copy(mug, 0.0).vertices, mug.vertices)
        moved = noisy_copy(mug, 2.0, seed=4).vertices - mug.vertices
        along = np.sum(moved * mug.vertex_normals, axis=1)
        assert np.allclose(np.linalg.norm(moved, axis=1), np.abs(along))  # only along the normal
        assert along.std() == pytest.approx(2.0, rel=0.1)
        assert noisy_copy(mug, 2.0, seed=4).label is None  # the camera does not know the class

    @pytest.mark.parametrize("noise", [-1.0, float("nan"), 1000.001, 1e300])
    def test_bad_noise(self, objects, noise):
        """Beyond MAX_NOISE_MM (1 m) the copy is no view of the object: refused by name, as is what is no noise."""
        with pytest.raises(InvalidArgumentError, match=r"noisy_copy: noise_mm must be a finite number in \[0, 1000\]"):
            noisy_copy(objects[0], noise)

    def test_negative_zero_noise_is_no_noise(self, objects):
        """-0.0 mm (what ``--noise-mm -0.0`` parses to) is no noise: it raised numpy's "scale < 0" ValueError, after
        the active run had generated its stores."""
        mug = objects[0]
        np.testing.assert_array_equal(noisy_copy(mug, -0.0, seed=3).vertices, mug.vertices)

    def test_noise_up_to_the_limit_is_kept_finite(self, objects):
        far = noisy_copy(objects[0], 1000.0, seed=2)
        assert np.isfinite(far.vertices).all()


def test_episode_figure(objects, tmp_path):
    from fusion.active.figure import plot_episode

    mug, _, visual = objects
    episode = run_episode(mug, visual, OrientationClassifier(), make_policy("random"), max_touches=2)
    path = plot_episode(episode, mug, tmp_path / "episode.png", label="a")
    assert path.is_file() and path.stat().st_size > 10_000


def _proposals(policy, visual, n: int = 5) -> list:
    """The first ``n`` planes ``policy`` proposes on ``visual`` as it goes (a classifier that learns nothing)."""
    state = ActiveState(visual, ConstantClassifier())
    for _ in range(n):
        state = ActiveState(visual, state.classifier, planes=[*state.planes, policy.propose(state)],
                            probabilities=[*state.probabilities, np.array([1 / 3] * 3)])
    return state.planes


def test_saliency_policy_takes_every_interest_pair_once_before_any_again(objects):
    """The saliency policy's contours are the guided strategy's pairs without repeats: as many distinct planes as
    the visual model has usable pairs, then the cycle starts again; the order is the policy seed's."""
    from tactile.touching import Toucher

    _, _, visual = objects
    state = ActiveState(visual, ConstantClassifier())
    usable = Toucher(visual, "guided", probes=state.probes, saliency_seed=4).pair_order(0).planes  # the policy's
    policy = make_policy("saliency", 4)
    for _ in range(len(usable) + 2):
        state = ActiveState(visual, state.classifier, planes=[*state.planes, policy.propose(state)],
                            probabilities=[*state.probabilities, np.array([1 / 3] * 3)])
    planes = state.planes
    assert all(any(same_plane(p, u) for u in usable) for p in planes)
    first = planes[: len(usable)]
    assert all(not same_plane(a, b) for i, a in enumerate(first) for b in first[i + 1:])  # each once
    # Another seed, another order (the first five proposals of each policy as it goes).
    assert len(usable) > 5
    mine, other = _proposals(make_policy("saliency", 4), visual), _proposals(make_policy("saliency", 5), visual)
    assert all(same_plane(a, b) for a, b in zip(mine, planes[:5]))  # same seed, same order
    assert not all(same_plane(a, b) for a, b in zip(mine, other))


def test_saliency_policy_given_the_visual_models_saliency_proposes_what_it_would_compute(objects):
    """A saliency computed once where the camera's view is processed (seed 4) gives the same proposals as the policy
    computing it with that seed; a saliency of another object is refused."""
    from perception.errors import SaliencyError
    from tactile.touching import Toucher

    mug, _, visual = objects
    proposals = lambda policy, n=4: _proposals(policy, visual, n)
    given = Toucher(visual, "guided", probes=25, saliency_seed=4).saliency
    own = proposals(make_policy("saliency", 4))
    assert all(same_plane(a, b) for a, b in zip(proposals(make_policy("saliency", 4, saliency=given)), own))
    other_view = Toucher(visual, "guided", probes=25, saliency_seed=9).saliency  # another turn of the view sphere
    assert not all(same_plane(a, b) for a, b in zip(proposals(make_policy("saliency", 4, saliency=other_view)), own))
    with pytest.raises(SaliencyError, match="saliency of"):
        proposals(make_policy("saliency", 4, saliency=Toucher(mug, "guided", probes=25).saliency), n=1)
    with pytest.raises(InvalidArgumentError, match="saliency policy takes"):
        make_policy("saliency", 4, candidates=3)
