"""Active touch in the Gymnasium environment: a random agent and the information policy, same env, same objects.

A small SVM learns from blind contours of 4 catalogue classes (3 instances each); the env then presents 4 other
instances in random poses, and each agent touches 4 contours per episode, predicting the class at every step.
Runs in about a minute on 2 cores: ``python examples/active_touch.py``.
"""

import gymnasium as gym
import numpy as np

from fusion.active import make_policy
from fusion.active.env import ENV_ID, PolicyAgent, observation_batch
from fusion.classifiers import make_classifier
from fusion.experiments.touch import touch_objects
from perception.shapes import make_object
from tactile import FSRSensor

CLASSES = ["bottle", "bowl", "box", "mug"]
sensor = FSRSensor(rows=16, cols=16)
training = [make_object(c, seed) for c in CLASSES for seed in range(3)]
classifier = make_classifier("svm").fit(touch_objects(training, CLASSES, "blind", 8, sensor=sensor, probes=10))

test_objects = [(c, 10) for c in CLASSES]  # instances the classifier never saw
env = gym.make(ENV_ID, objects=test_objects, class_names=CLASSES, step_limit=4, sensor=sensor, probes=10)
agents = {"random": None, "information": PolicyAgent(make_policy("information", candidates=16), classifier)}
for name, agent in agents.items():
    correct = np.zeros(4)
    for episode in range(4):
        obs, info = env.reset(seed=episode)
        env.action_space.seed(episode)
        if agent is not None:
            agent.reset(env.unwrapped.visual_model)
        posterior = np.zeros(len(CLASSES))
        for step in range(4):
            if agent is None:  # random plane; it classifies with the same classifier to score its prediction
                action = env.action_space.sample()
                action["prediction"] = posterior.astype(np.float32)
            else:
                action = agent.act()
            obs, reward, terminated, truncated, info = env.step(action)
            if agent is None:
                if obs["missed"][0] == 0:
                    posterior = posterior + np.log(np.maximum(
                        classifier.predict_proba(observation_batch(obs, classifier.sensor_spec_))[0], 1e-12))
                correct[step] += CLASSES[int(np.argmax(posterior))] == CLASSES[info["prediction"]["target"]]
            else:
                agent.observe(obs)
                correct[step] += CLASSES[int(np.argmax(agent.state.posterior))] == CLASSES[info["prediction"]["target"]]
    print(f"{name:12s} accuracy after 1..4 touches: {', '.join(f'{c / 4:.2f}' for c in correct)}")
