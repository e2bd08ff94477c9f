"""Active touch as a Gymnasium environment in ``ap_gym``'s active-classification convention.

Each episode (:class:`ActiveTouchEnv`) draws an object from its set (seeded by ``reset(seed=...)``), turns it by
a uniformly random rotation (``any_pose``) and shows the agent what a camera would: a point cloud of the
*visual model* (a noisy copy of the mesh, ``visual_noise_mm``). Each step the agent sends

- ``action``: a 3-vector, the normal of the next contour plane through the visual model's centre (any length
  above 1e-6; shorter vectors mean +z), in the observed (object) frame;
- ``prediction``: class logits (C,), scored by ``ap_gym``'s normalised cross-entropy (the reward is minus that loss);

and observes the tactile sequence of that contour touched on the true object: ``frames`` (P, rows, cols) gap
images, mm; ``cues`` (P, 6) the pose-free kinesthetic cues (:data:`fusion.cues.INVARIANT_NAMES`);
``positions`` (P, 3) mm from the visual centre, ``normals``, ``tangents`` (P, 3), ``pad_sides_mm`` (P,),
``plane_normal`` (3,), ``missed`` (1,) 1 where the plane missed the object (all else zero), ``points`` (N, 3) the
visual point cloud, mm from its centre, and ``time_step`` (1,) steps taken / ``step_limit``. Episodes end
after ``step_limit`` touches. :func:`observation_batch` turns an observation into the
:class:`~tactile.explore.SequenceBatch` a classifier reads; ``env.unwrapped.visual_model`` is the visual mesh
a planner may use (:mod:`fusion.active.policies`). Same seed, same bytes.

Registered as ``visuotactile/ActiveTouch-v0`` when this module is imported, e.g.
``gymnasium.make("fusion.active.env:visuotactile/ActiveTouch-v0")``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import ap_gym
import gymnasium as gym
import numpy as np

from fusion.active.episode import touch_seed
from fusion.active.policies import noisy_copy
from fusion.cues import INVARIANT_NAMES, kinesthetic_cues
from perception.errors import ContourError, InvalidArgumentError, InvalidMeshError
from perception.geometry import ObjectModel, random_rotation, rotate
from perception.limits import check_bytes, check_count
from tactile.contours import Plane
from tactile.explore import SequenceBatch
from tactile.sensor import FSRSensor
from tactile.touching import touch

ENV_ID = "visuotactile/ActiveTouch-v0"
#: The default object set: built-in catalogue classes x seeds (small, procedural, no data needed).
DEFAULT_OBJECTS = tuple((c, s) for c in ("bottle", "bowl", "box", "mug") for s in (0, 1))


#: Largest |logit| a prediction may hold: the loss (scored here in float64) then stays finite; a float32 softmax
#: overflowed on differences of 3e38 (a reward of -inf or NaN).
MAX_LOGIT = 1e30


def _load(objects) -> list[ObjectModel]:
    from perception.shapes import make_object

    if isinstance(objects, (str, bytes, ObjectModel)) or not hasattr(objects, "__iter__"):
        raise InvalidArgumentError(f"ActiveTouchEnv: objects must be a list of ObjectModels or (class, seed) pairs, "
                                   f"got {type(objects).__name__}")
    models = []
    for item in objects:
        model = item if isinstance(item, ObjectModel) else (
            make_object(*item) if isinstance(item, (tuple, list)) and len(item) == 2 else None)
        if model is None:
            raise InvalidArgumentError(f"ActiveTouchEnv: expected ObjectModels or (class, seed) pairs, got {item!r}")
        if model.label is None:
            raise InvalidArgumentError(f"ActiveTouchEnv: object {model.name} has no label (class)")
        if not model.triangle_areas.sum() > 0:  # no surface to sample the camera's points from or to touch
            raise InvalidMeshError(f"ActiveTouchEnv: object {model.name} has zero surface area")
        models.append(model)
    if not models:
        raise InvalidArgumentError("ActiveTouchEnv: no objects given")
    return models


class ActiveTouchEnv(ap_gym.ActiveClassificationEnv):
    """Recognise an object by touching contours of your choice (see the module docstring).

    Args:
        objects: labelled :class:`ObjectModel` s or catalogue (class, seed) pairs (default
            :data:`DEFAULT_OBJECTS`).
        class_names: the classes (prediction order; default: the objects' labels, sorted).
        step_limit: touches per episode.
        sensor: the FSR pad (default 16 x 16 taxels); probes: probes per contour.
        any_pose: turn each episode's object by a random rotation.
        visual_noise_mm: the visual model's vertex noise along the normals, mm.
        cloud_points: points of the observed visual point cloud.

    Raises:
        InvalidArgumentError: no or unlabelled objects, a label not in ``class_names``, fewer than two or repeated
            class names, bad counts or noise, observations too large to allocate, a render mode (there is none).
        InvalidMeshError: an object without surface area.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, objects=None, *, class_names=None, step_limit: int = 8, sensor: FSRSensor | None = None,
                 probes: int = 10, any_pose: bool = True, visual_noise_mm: float = 1.0, cloud_points: int = 256,
                 render_mode: str | None = None) -> None:
        self.objects = _load(DEFAULT_OBJECTS if objects is None else objects)
        labels = sorted({m.label for m in self.objects})
        self.class_names = list(class_names) if class_names is not None else labels
        missing = sorted(set(labels) - set(self.class_names))
        if missing:
            raise InvalidArgumentError(f"ActiveTouchEnv: labels {missing} are not in class_names {self.class_names}")
        if len(set(self.class_names)) != len(self.class_names) or len(self.class_names) < 2:
            raise InvalidArgumentError(f"ActiveTouchEnv: needs two or more distinct class names, got {self.class_names}")
        for name, value, low in (("step_limit", step_limit, 1), ("probes", probes, 2), ("cloud_points", cloud_points, 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise InvalidArgumentError(f"ActiveTouchEnv: {name} must be an integer >= {low}, got {value!r}")
        check_count("probes", probes, "ActiveTouchEnv: probes")
        if isinstance(visual_noise_mm, bool) or not isinstance(visual_noise_mm, (int, float, np.number)) \
                or not np.isfinite(visual_noise_mm) or visual_noise_mm < 0:
            raise InvalidArgumentError(f"ActiveTouchEnv: visual_noise_mm must be a number >= 0, got {visual_noise_mm!r}")
        if render_mode is not None:
            raise InvalidArgumentError(f"ActiveTouchEnv: render_mode {render_mode!r} is not supported (there is none); "
                                       "draw an episode with fusion.active.figure.plot_episode")
        self.sensor = sensor or FSRSensor(rows=16, cols=16)
        self.probes, self.step_limit, self.cloud_points = int(probes), int(step_limit), int(cloud_points)
        self.any_pose, self.visual_noise_mm = bool(any_pose), float(visual_noise_mm)
        # float32 observations: frames, the point cloud and the per-probe arrays
        values = self.probes * (self.sensor.rows * self.sensor.cols + 16) + 3 * self.cloud_points
        check_bytes(4 * values, f"ActiveTouchEnv: an observation of {self.probes} probes and {self.cloud_points} points")
        self.render_mode = render_mode
        super().__init__(len(self.class_names), gym.spaces.Box(-1.0, 1.0, (3,), np.float32))
        p, (rows, cols) = self.probes, (self.sensor.rows, self.sensor.cols)
        # Everything in mm lies within the largest object's size of the centre (noise, pads and gaps included).
        bound = 2.0 * max(max(m.size for m in self.objects), self.sensor.side_mm, self.sensor.range_mm,
                          self.sensor.saturation)
        box = lambda shape: gym.spaces.Box(-bound, bound, shape, np.float32)
        self.observation_space = gym.spaces.Dict({
            "frames": box((p, rows, cols)),
            "cues": box((p, len(INVARIANT_NAMES))),
            "positions": box((p, 3)),
            "normals": gym.spaces.Box(-1.0, 1.0, (p, 3), np.float32),
            "tangents": gym.spaces.Box(-1.0, 1.0, (p, 3), np.float32),
            "pad_sides_mm": box((p,)),
            "plane_normal": gym.spaces.Box(-1.0, 1.0, (3,), np.float32),
            "missed": gym.spaces.Box(0.0, 1.0, (1,), np.float32),
            "points": box((self.cloud_points, 3)),
            "time_step": gym.spaces.Box(0.0, 1.0, (1,), np.float32),
        })
        self.visual_model: ObjectModel | None = None
        self._true: ObjectModel | None = None
        self._target, self._step_count, self._episode_seed, self._points = 0, 0, 0, None

    def _blank(self) -> dict[str, np.ndarray]:
        obs = {k: np.zeros(space.shape, np.float32) for k, space in self.observation_space.spaces.items()}
        obs["points"] = self._points.copy()
        obs["time_step"] = np.array([self._step_count / self.step_limit], np.float32)
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        index = int(rng.integers(len(self.objects)))
        model = self.objects[index]
        rotation = random_rotation(rng) if self.any_pose else np.eye(3)
        self._true = rotate(model, rotation) if self.any_pose else model
        self._episode_seed = int(rng.integers(2**31 - 1))
        self.visual_model = noisy_copy(self._true, self.visual_noise_mm, self._episode_seed, name="visual")
        # The camera's point cloud: area-weighted surface samples of the visual model, mm from its centre.
        visual = self.visual_model
        area = visual.triangle_areas / visual.triangle_areas.sum()
        tri = rng.choice(len(area), size=self.cloud_points, p=area)
        u, v = rng.random((2, self.cloud_points))
        flip = u + v > 1
        u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
        corners = visual.vertices[visual.triangles[tri]]
        points = corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])
        self._points = (points - visual.center).astype(np.float32)
        self._target = self.class_names.index(model.label)
        self._step_count = 0
        return self._blank(), {"object": model.name}

    def step(self, action):
        """One touch and one prediction: ``action`` = {"action": plane normal (3,), "prediction": logits (C,)}.

        Raises:
            InvalidArgumentError: not such a dict, a normal that is not a finite real 3-vector, or logits that are
                not C finite reals within +-:data:`MAX_LOGIT`.
            gymnasium.error.ResetNeeded: before ``reset()`` or after the episode ended.
        """
        if not isinstance(action, dict) or not {"action", "prediction"} <= set(action):
            raise InvalidArgumentError(f"ActiveTouchEnv: step takes {{'action': normal, 'prediction': logits}}, got "
                                       f"{type(action).__name__}")
        problem = f"the prediction must be {len(self.class_names)} finite real logits within +-{MAX_LOGIT:g}"
        try:
            logits = np.asarray(action["prediction"])
        except (TypeError, ValueError) as exc:  # a ragged list
            raise InvalidArgumentError(f"ActiveTouchEnv: {problem} ({exc})") from None
        # float64 for the checks and the loss: float16 logits of 6e4 overflowed its softmax to a reward of -inf
        values = logits.astype(np.float64) if logits.dtype.kind in "fiu" else None
        if values is None or values.shape != (len(self.class_names),) \
                or not (np.isfinite(values).all() and np.abs(values).max() <= MAX_LOGIT):
            raise InvalidArgumentError(f"ActiveTouchEnv: {problem}, got shape {logits.shape}, dtype {logits.dtype}")
        return super().step({**action, "prediction": values})

    def _step(self, action, prediction):
        if self._true is None:
            raise gym.error.ResetNeeded("ActiveTouchEnv: call reset() before step()")
        if self._step_count >= self.step_limit:
            raise gym.error.ResetNeeded("ActiveTouchEnv: the episode has ended; call reset()")
        try:
            raw = np.asarray(action)
        except (TypeError, ValueError):  # a ragged list
            raw = np.asarray(None)
        if raw.dtype.kind not in "fiu" or raw.size != 3:
            raise InvalidArgumentError(f"ActiveTouchEnv: the action must be a real 3-vector (a plane normal), got "
                                       f"{action!r}")
        normal = raw.astype(np.float64).reshape(3)
        if not np.isfinite(normal).all():
            raise InvalidArgumentError(f"ActiveTouchEnv: the action must be a finite 3-vector, got {action!r}")
        largest = np.abs(normal).max()
        # the length as the largest component times the norm of the scaled vector: no overflow for 1e300
        length = largest * np.linalg.norm(normal / largest) if largest > 0 else 0.0
        normal = normal / largest if largest > 0 else normal
        if length < 1e-6:
            normal = np.array([0.0, 0.0, 1.0])
        plane = Plane(self.visual_model.center, normal)
        seed = touch_seed(self._episode_seed, self._step_count)
        self._step_count += 1
        obs = self._blank()
        obs["plane_normal"] = plane.normal.astype(np.float32)
        try:
            sequence = touch(self._true, "blind", 1, self.sensor, self.probes, seed=seed, planes=[plane])[0]
        except ContourError:
            obs["missed"][:] = 1.0
        else:
            sequence.label = None
            batch = SequenceBatch.from_sequences([sequence], sensor_spec=self.sensor.spec())
            obs["frames"] = sequence.frames.astype(np.float32)
            obs["cues"] = kinesthetic_cues(batch, "invariant")[0]
            obs["positions"] = (sequence.positions - self.visual_model.center).astype(np.float32)
            obs["normals"] = np.clip(sequence.normals, -1, 1).astype(np.float32)
            obs["tangents"] = np.clip(sequence.tangents, -1, 1).astype(np.float32)
            obs["pad_sides_mm"] = sequence.pad_sides_mm.astype(np.float32)
        terminated = self._step_count >= self.step_limit
        return obs, 0.0, terminated, False, {}, np.int64(self._target)


def observation_batch(obs: dict, sensor_spec: dict) -> SequenceBatch:
    """The one-sequence :class:`SequenceBatch` of an :class:`ActiveTouchEnv` observation (positions relative to
    the plane point, the visual centre), for a classifier trained with ``sensor_spec``.

    Raises:
        InvalidArgumentError: the observation is of a missed touch (nothing was felt).
    """
    if float(np.asarray(obs["missed"]).reshape(-1)[0]) > 0:
        raise InvalidArgumentError("observation_batch: the touch missed the object; there is no sequence")
    one = lambda key: np.asarray(obs[key])[None]
    return SequenceBatch(frames=one("frames"), normals=one("normals"), positions=one("positions"),
                         tangents=one("tangents"), pad_sides_mm=one("pad_sides_mm"), plane_points=np.zeros((1, 3)),
                         plane_normals=np.asarray(obs["plane_normal"], np.float64)[None],
                         labels=np.array([-1]), object_ids=np.array([0]), sensor_spec=dict(sensor_spec))


class PolicyAgent:
    """A :mod:`fusion.active.policies` policy acting in an :class:`ActiveTouchEnv`: it plans on the env's visual
    model, classifies each observation with ``classifier`` (trained with the env's sensor and probes) and predicts
    the log of the fused posterior.

    Call :meth:`reset` with ``env.unwrapped.visual_model`` after each ``env.reset``, then :meth:`act` per step.
    """

    def __init__(self, policy, classifier) -> None:
        from fusion.active.policies import ActiveState

        self.policy, self.classifier, self._state_type = policy, classifier, ActiveState
        self.state = None

    def reset(self, visual_model: ObjectModel) -> None:
        self.state, self._pending = self._state_type(visual_model, self.classifier), None

    def act(self) -> dict[str, np.ndarray]:
        """The next action (the proposed plane's normal) and prediction (log of the fused posterior so far; the
        env's class order must be the classifier's)."""
        self._pending = self.policy.propose(self.state)
        logits = np.log(np.maximum(self.state.posterior, 1e-12)).astype(np.float32)
        return {"action": self._pending.normal.astype(np.float32), "prediction": logits}

    def observe(self, obs: dict) -> None:
        """Add the touch the last action made (a missed touch adds a uniform output)."""
        n = len(self.state.classes)
        try:
            batch = observation_batch(obs, self.classifier.sensor_spec_)
        except InvalidArgumentError:
            proba = np.full(n, 1.0 / n)
        else:
            proba = np.asarray(self.classifier.predict_proba(batch), dtype=np.float64)[0]
        self.state.planes.append(self._pending)
        self.state.probabilities.append(proba)


def register_envs() -> None:
    """Register :data:`ENV_ID` with Gymnasium (once)."""
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point="fusion.active.env:ActiveTouchEnv")


register_envs()

__all__ = ["DEFAULT_OBJECTS", "ENV_ID", "ActiveTouchEnv", "PolicyAgent", "observation_batch", "register_envs"]
