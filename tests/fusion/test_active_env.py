"""The active-touch Gymnasium environment: Gymnasium's checker, seeded episodes byte for byte, vectorised envs,
observations a classifier can read again, and bad settings."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")
pytest.importorskip("ap_gym")

from gymnasium.utils.env_checker import check_env

from fusion.active.env import ENV_ID, ActiveTouchEnv, observation_batch
from fusion.cues import kinesthetic_cues
from perception.errors import InvalidArgumentError
from tactile.sensor import FSRSensor

SMALL = {"objects": [("box", 0), ("mug", 0)], "step_limit": 3, "sensor": FSRSensor(rows=8, cols=8), "probes": 6,
         "cloud_points": 32}


def episode_bytes(seed: int) -> bytes:
    env = ActiveTouchEnv(**SMALL)
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    out = [np.concatenate([v.ravel() for v in obs.values()]).tobytes()]
    done = False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        out += [np.concatenate([v.ravel() for v in obs.values()]).tobytes(), np.float64(reward).tobytes()]
        done = terminated or truncated
    return b"".join(out)


def test_passes_gymnasium_check_env():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ap_gym's logit space is unbounded by design; the checker warns
        check_env(ActiveTouchEnv(**SMALL))


def test_seeded_random_episode_is_reproducible_byte_for_byte():
    first = episode_bytes(3)
    assert first == episode_bytes(3)
    assert first != episode_bytes(4)


def test_vectorised():
    envs = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync", **SMALL)
    obs, _ = envs.reset(seed=0)
    assert obs["frames"].shape == (2, 6, 8, 8) and obs["points"].shape == (2, 32, 3)
    envs.action_space.seed(0)
    obs, reward, terminated, _, _ = envs.step(envs.action_space.sample())
    assert reward.shape == (2,) and np.isfinite(reward).all() and not terminated.any()
    assert (np.abs(obs["frames"]).sum(axis=(1, 2, 3)) > 0).all() or obs["missed"].any()
    envs.close()


def test_observation_reads_back_as_a_sequence():
    """The observed pose-free cues are those of the sequence rebuilt from the observation (cues do not depend
    on where the origin is); a zero action touches the plane normal to +z; the episode ends at the limit."""
    env = ActiveTouchEnv(**SMALL)
    env.reset(seed=1)
    zero = {"action": np.zeros(3, np.float32), "prediction": np.zeros(2, np.float32)}
    obs, reward, terminated, _, info = env.step(zero)
    np.testing.assert_array_equal(obs["plane_normal"], [0, 0, 1])
    batch = observation_batch(obs, env.sensor.spec())
    np.testing.assert_allclose(kinesthetic_cues(batch, "invariant")[0], obs["cues"], atol=1e-3)
    assert reward == pytest.approx(-info["prediction"]["loss"])  # uniform logits: ap_gym's normalised loss
    for _ in range(2):
        *_, terminated, _, _ = env.step(zero)
    assert terminated


@pytest.mark.parametrize("kwargs, match", [({"objects": []}, "no objects"), ({"step_limit": 0}, "step_limit"),
                                           ({"class_names": ["box"]}, "not in class_names"),
                                           ({"visual_noise_mm": -1.0}, "visual_noise_mm")])
def test_bad_settings(kwargs, match):
    with pytest.raises(InvalidArgumentError, match=match):
        ActiveTouchEnv(**{**SMALL, **kwargs})


@pytest.mark.parametrize("prediction", [[np.nan, 0.0], [np.inf, np.inf], [3e38, -3e38], [0.0, 0.0, 0.0], [0.0],
                                        ["a", "b"], [1 + 2j, 0], [[0.0], 0.0]])
def test_predictions_that_would_make_the_reward_not_finite_are_refused(prediction):
    """NaN / Inf logits gave a NaN reward, float32 logits of +-3e38 a reward of -inf (the loss's softmax
    overflows), three logits in a two-class env a reward as if all were fine."""
    env = ActiveTouchEnv(**SMALL)
    env.reset(seed=0)
    with pytest.raises(InvalidArgumentError, match="the prediction must be 2 finite real logits"):
        env.step({"action": np.ones(3), "prediction": prediction if isinstance(prediction[0], list)
                  else np.asarray(prediction)})
    _, reward, *_ = env.step({"action": np.ones(3), "prediction": np.array([1e30, -1e30])})  # the largest allowed
    assert np.isfinite(reward)


@pytest.mark.parametrize("action, match", [
    (np.ones(4), "real 3-vector"), (np.float64(1.0), "real 3-vector"), (None, "real 3-vector"), ("abc", "real 3-vector"),
    ({"x": 1}, "real 3-vector"), (np.array([1 + 1j, 0, 0]), "real 3-vector"), (np.array(["1", "2", "3"]), "real 3-vector"),
    (np.array([np.nan, 0, 0]), "finite 3-vector"), ([[1.0], 2.0, 3.0], "real 3-vector"),
])
def test_bad_actions_name_the_problem(action, match):
    env = ActiveTouchEnv(**SMALL)
    env.reset(seed=0)
    with pytest.raises(InvalidArgumentError, match=match):
        env.step({"action": action, "prediction": np.zeros(2)})
    with pytest.raises(InvalidArgumentError, match="step takes"):
        env.step({"action": np.ones(3)})


def test_float16_logits_give_a_finite_reward():
    """float16 logits of +-6e4 pass every bound, but the loss's softmax overflowed in float16: a reward of -inf."""
    env = ActiveTouchEnv(**SMALL)
    env.reset(seed=0)
    for logits in ([60000.0, -60000.0], [-60000.0, 60000.0]):
        _, reward, *_ = env.step({"action": np.ones(3), "prediction": np.array(logits, np.float16)})
        assert np.isfinite(reward)


def test_a_short_normal_means_up_by_its_length():
    """Shorter than 1e-6 (its length, not its largest component): the plane normal to +z."""
    env = ActiveTouchEnv(**SMALL)
    env.reset(seed=0)
    short, _, *_ = env.step({"action": np.full(3, 5e-7), "prediction": np.zeros(2)})  # length 8.7e-7
    long, _, *_ = env.step({"action": np.full(3, 8e-7), "prediction": np.zeros(2)})  # length 1.4e-6
    np.testing.assert_array_equal(short["plane_normal"], [0, 0, 1])
    np.testing.assert_allclose(long["plane_normal"], np.full(3, 1 / np.sqrt(3)), rtol=1e-6)


def test_a_huge_normal_touches_the_plane_of_its_direction():
    """1e300 * (1, 2, 2): the norm overflowed (a warning); the plane is that of (1, 2, 2) / 3."""
    env = ActiveTouchEnv(**SMALL)
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        obs, *_ = env.step({"action": np.array([1e300, 2e300, 2e300]), "prediction": np.zeros(2)})
    np.testing.assert_allclose(obs["plane_normal"], np.array([1, 2, 2]) / 3, atol=1e-7)


def test_stepping_past_the_end_asks_for_a_reset():
    """After the last touch the time step would leave its space (2 / 1 after one more step of a 1-step episode)."""
    env = ActiveTouchEnv(**{**SMALL, "step_limit": 1})
    env.reset(seed=0)
    *_, terminated, _, _ = env.step({"action": np.ones(3), "prediction": np.zeros(2)})
    assert terminated
    with pytest.raises(gym.error.ResetNeeded, match="ended"):
        env.step({"action": np.ones(3), "prediction": np.zeros(2)})
    env.reset(seed=1)
    env.step({"action": np.ones(3), "prediction": np.zeros(2)})


@pytest.mark.parametrize("kwargs, match", [
    ({"objects": [("box", 0), ("box", 1)]}, "two or more distinct class names"),
    ({"class_names": ["box", "mug", "box"]}, "two or more distinct class names"),
    ({"render_mode": "human"}, "render_mode 'human' is not supported"),
    ({"visual_noise_mm": "a"}, "visual_noise_mm must be a number"),
    ({"objects": 5}, "objects must be a list"),
    ({"probes": 10**7}, "above the limit"),
    ({"cloud_points": 10**12}, "ActiveTouchEnv: an observation of 6 probes and 1000000000000 points"),
])
def test_more_bad_settings(kwargs, match):
    with pytest.raises(InvalidArgumentError, match=match):
        ActiveTouchEnv(**{**SMALL, **kwargs})


def test_an_object_without_area_is_refused_when_the_env_is_made():
    """A mesh whose only triangle has collinear corners: reset divided 0 by 0 (numpy's 'probabilities contain NaN')."""
    from perception.errors import InvalidMeshError
    from perception.geometry import ObjectModel
    from perception.shapes import make_object

    stick = ObjectModel(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]), name="stick", label="box")
    with pytest.raises(InvalidMeshError, match="stick has zero surface area"):
        ActiveTouchEnv(**{**SMALL, "objects": [stick, make_object("mug", 0)]})
