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
