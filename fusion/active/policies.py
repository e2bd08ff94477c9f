"""Next-touch policies: given what a robot knows so far, propose the plane of the next contour.

What a policy may read (:class:`ActiveState`) is all a robot would have: the **visual model** (the camera's
reconstruction of the object, or a noisy copy of its mesh standing in for one), the contours touched so far
with the classifier's probabilities for each, and the trained classifier. The contract, tested:

- a policy never reads the true mesh, the label, or the outcome of a touch before making it (the state holds
  none of them; the true object exists only in :func:`fusion.active.episode.run_episode`, which touches it);
- with the same visual model and the same touch outcomes so far, it proposes the same next plane whatever the
  true object is (its choices are a function of the state and its own seed); its first choice depends on the
  visual model alone.

Every plane passes through the visual model's centre; the visual and true models share one frame (mm), so a
plane chosen on one is touched on the other. Policies (:data:`POLICIES`):

- ``"random"``: blind, two random vertices of the visual model (the ``"blind"`` sampling strategy).
- ``"saliency"``: the paper's, two of the visual model's multiview interest points (``"guided"``).
- ``"information"``: expected information gain. ``candidates`` blind planes of the visual model are touched
  *there* (simulated with :func:`tactile.touch`, ``variants`` times: once as planned and then with pose jitter
  of ``jitter_mm``, since the finger lands only near the plan and the visual model is only near the truth) and
  classified, once per visual model and cached. Each step then picks the untouched candidate whose simulated
  outcomes q move the current posterior p most: the mean over variants of KL(p * q / Z || p) in nats, the
  expected information gain of the touch when its outcome is drawn from the simulated ones (the log rule's
  Bayesian update, :func:`information_gain`). With a uniform posterior this picks the contour the classifier
  reads most confidently; later, the one that best separates the hypotheses still in doubt.
"""

from __future__ import annotations

import hashlib
import logging
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from fusion.decide import PROBA_FLOOR, fuse_touches
from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import ObjectModel
from tactile import sampling
from tactile.contours import Plane
from tactile.explore import SequenceBatch, TactileSequence
from tactile.sensor import FSRSensor
from tactile.touching import Toucher, touch

log = logging.getLogger(__name__)

POLICIES = ("random", "saliency", "information")


@dataclass
class ActiveState:
    """What a policy may know before the next touch (nothing about the true object).

    Attributes:
        visual: the camera's model of the object (reconstruction or noisy copy), mm; never the true mesh.
        classifier: the fitted classifier (``predict_proba`` over sequences, ``classes_``).
        planes: the planes touched so far, in order.
        probabilities: the classifier's (C,) probabilities of each touch so far (``classes_`` order).
        sequences: the tactile sequences of the touches so far.
    """

    visual: ObjectModel
    classifier: object
    planes: list[Plane] = field(default_factory=list)
    probabilities: list[np.ndarray] = field(default_factory=list)
    sequences: list[TactileSequence] = field(default_factory=list)

    @property
    def step(self) -> int:
        """Touches made so far."""
        return len(self.planes)

    @property
    def classes(self) -> list[str]:
        return [str(c) for c in self.classifier.classes_]

    @property
    def posterior(self) -> np.ndarray:
        """(C,) the touches so far fused by the log rule (uniform before the first)."""
        n = len(self.classes)
        if not self.probabilities:
            return np.full(n, 1.0 / n)
        return fuse_touches(np.asarray(self.probabilities, dtype=np.float64), rule="log")

    def sensor(self) -> FSRSensor:
        return self.classifier.sensor()

    @property
    def probes(self) -> int:
        return int(self.classifier.probes)


def information_gain(posterior, outcomes) -> np.ndarray:
    """KL(p * q / Z || p) in nats for each outcome q (rows of ``outcomes``, (..., C)) given the posterior p (C,):
    how far fusing q by the log rule moves p (probabilities floored at ``PROBA_FLOOR``). Never negative.

    Raises:
        InvalidArgumentError: shapes that do not match, or negative / non-finite probabilities.
    """
    p = np.asarray(posterior, dtype=np.float64)
    q = np.asarray(outcomes, dtype=np.float64)
    if p.ndim != 1 or q.ndim < 1 or q.shape[-1] != p.shape[0] or p.shape[0] < 1:
        raise InvalidArgumentError(f"information_gain: posterior (C,) and outcomes (..., C), got {p.shape}, {q.shape}")
    if not (np.isfinite(p).all() and np.isfinite(q).all()) or (p < 0).any() or (q < 0).any():
        raise InvalidArgumentError("information_gain: probabilities must be finite and non-negative")
    log_p = np.log(np.maximum(p / max(p.sum(), PROBA_FLOOR), PROBA_FLOOR))
    log_new = log_p + np.log(np.maximum(q, PROBA_FLOOR))
    log_new -= log_new.max(axis=-1, keepdims=True)
    new = np.exp(log_new)
    new /= new.sum(axis=-1, keepdims=True)
    log_new_norm = np.log(np.maximum(new, PROBA_FLOOR))
    return np.maximum(np.sum(new * (log_new_norm - log_p), axis=-1), 0.0)


def visual_key(model: ObjectModel) -> str:
    """A digest of the visual model's geometry (vertices and triangles): what the per-model caches key on."""
    return hashlib.sha256(model.vertices.tobytes() + model.triangles.tobytes()).hexdigest()[:16]


def same_plane(a: Plane, b: Plane) -> bool:
    """Whether two planes are the same (same point, normal equal up to sign)."""
    return bool(np.allclose(a.point, b.point, atol=1e-9) and abs(abs(float(a.normal @ b.normal)) - 1.0) < 1e-12)


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidArgumentError(f"policy seed must be an integer >= 0, got {seed!r}")
    return int(seed)


class Policy:
    """Base class: ``propose(state) -> Plane`` (see the module docstring for the contract).

    Per visual model a policy keeps a :class:`~tactile.touching.Toucher` (planes cut once) and whatever it
    computed (saliency, simulated candidates), keyed by the model's geometry (:func:`visual_key`); the last
    ``cache_size`` models are kept.
    """

    name = "policy"
    strategy = "blind"

    def __init__(self, seed: int = 0, *, cache_size: int = 8) -> None:
        self.seed = _check_seed(seed)
        self.cache_size = int(cache_size)
        self._cache: dict[str, dict] = {}
        self._keys: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.planning_seconds: list[float] = []

    def _entry(self, state: ActiveState) -> dict:
        geometry = self._keys.get(state.visual)
        if geometry is None:
            geometry = self._keys[state.visual] = visual_key(state.visual)
        key = f"{geometry}-{state.probes}"
        entry = self._cache.get(key)
        if entry is None:
            if len(self._cache) >= self.cache_size:
                self._cache.pop(next(iter(self._cache)))
            entry = self._cache[key] = {"key": key,
                                        "toucher": Toucher(state.visual, self.strategy, probes=state.probes,
                                                           saliency_seed=self.seed)}
        return entry

    def _rng(self, entry: dict, step: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, int(entry["key"][:16], 16) % 2**32, step])

    def propose(self, state: ActiveState) -> Plane:
        """The plane of the next contour (through the visual model's centre).

        Raises:
            ContourError: no plane that cuts the visual model could be found.
        """
        start = time.perf_counter()
        plane = self._propose(state)
        self.planning_seconds.append(time.perf_counter() - start)
        return plane

    def _propose(self, state: ActiveState) -> Plane:
        entry = self._entry(state)
        toucher = entry["toucher"]
        rng = self._rng(entry, state.step)
        for _ in range(sampling.MAX_DRAWS):
            plane = toucher.draw(rng)
            if not any(same_plane(plane.plane, p) for p in state.planes):
                return plane.plane
        return plane.plane  # every draw repeated a touched plane (a tiny candidate pool): touch it again


class RandomPolicy(Policy):
    """Blind: a plane through the visual model's centre and two of its vertices drawn at random (seeded by
    (seed, visual model, step))."""

    name, strategy = "random", "blind"


class SaliencyPolicy(Policy):
    """The paper's: a plane through the visual model's centre and two of its multiview interest points."""

    name, strategy = "saliency", "guided"


class InformationPolicy(Policy):
    """Expected information gain over ``candidates`` simulated contours (see the module docstring).

    Args:
        candidates: planes simulated per visual model (the candidate budget).
        variants: simulated touches per candidate (the first as planned, the others with ``jitter_mm``).
        jitter_mm: pose jitter of the extra variants, mm.
    """

    name, strategy = "information", "blind"

    def __init__(self, seed: int = 0, *, candidates: int = 24, variants: int = 2, jitter_mm: float = 1.0,
                 cache_size: int = 8) -> None:
        super().__init__(seed, cache_size=cache_size)
        for label, value in (("candidates", candidates), ("variants", variants)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InvalidArgumentError(f"information policy: {label} must be an integer >= 1, got {value!r}")
        if isinstance(jitter_mm, bool) or not np.isfinite(jitter_mm) or jitter_mm < 0:
            raise InvalidArgumentError(f"information policy: jitter_mm must be a finite number >= 0, got {jitter_mm!r}")
        self.candidates, self.variants, self.jitter_mm = int(candidates), int(variants), float(jitter_mm)
        #: Seconds spent simulating candidates (once per visual model), per model.
        self.simulation_seconds: list[float] = []

    def simulated(self, state: ActiveState) -> tuple[list[Plane], np.ndarray]:
        """The candidate planes of the visual model and their simulated outcomes (M, variants, C), computed once
        per (visual model, classifier)."""
        entry = self._entry(state)
        cached = entry.get("outcomes")
        if cached is not None and cached[0] is state.classifier:
            return entry["planes"], cached[1]
        start = time.perf_counter()
        toucher = entry["toucher"]
        rng = np.random.default_rng([self.seed, int(entry["key"][:16], 16) % 2**32, 2**31])
        planes: list[Plane] = []
        for _ in range(self.candidates * sampling.MAX_DRAWS):
            if len(planes) == self.candidates:
                break
            plane = toucher.draw(rng).plane
            if not any(same_plane(plane, p) for p in planes):
                planes.append(plane)
        if not planes:
            raise ContourError(f"{state.visual.name}: no candidate plane cuts the visual model")
        sensor, probes = state.sensor(), state.probes
        outcomes = []
        for v in range(self.variants):
            sequences = touch(state.visual, "blind", len(planes), sensor, probes, seed=self.seed + v,
                              planes=planes, jitter_mm=self.jitter_mm if v else 0.0)
            batch = SequenceBatch.from_sequences(sequences, class_names=state.classes, sensor_spec=sensor.spec())
            outcomes.append(np.asarray(state.classifier.predict_proba(batch), dtype=np.float64))
        outcomes = np.stack(outcomes, axis=1)
        entry["planes"], entry["outcomes"] = planes, (state.classifier, outcomes)
        self.simulation_seconds.append(time.perf_counter() - start)
        return planes, outcomes

    def scores(self, state: ActiveState) -> np.ndarray:
        """(M,) expected information gain (nats) of each candidate under the current posterior; touched
        candidates score -inf."""
        planes, outcomes = self.simulated(state)
        gain = information_gain(state.posterior, outcomes).mean(axis=1)
        touched = np.array([any(same_plane(c, p) for p in state.planes) for c in planes])
        return np.where(touched, -np.inf, gain)

    def _propose(self, state: ActiveState) -> Plane:
        planes, _ = self.simulated(state)
        scores = self.scores(state)
        if not np.isfinite(scores).any():  # every candidate touched: touch the best again
            scores = information_gain(state.posterior, self.simulated(state)[1]).mean(axis=1)
        return planes[int(np.argmax(scores))]


def make_policy(name: str, seed: int = 0, **options) -> Policy:
    """A new policy by name (:data:`POLICIES`); ``options`` go to :class:`InformationPolicy`.

    Raises:
        InvalidArgumentError: unknown name, or options for a policy that takes none.
    """
    if name == "information":
        return InformationPolicy(seed, **options)
    if name not in POLICIES:
        raise InvalidArgumentError(f"unknown touch policy {name!r}; choose one of {', '.join(POLICIES)}")
    if options:
        raise InvalidArgumentError(f"the {name} policy takes no options, got {sorted(options)}")
    return {"random": RandomPolicy, "saliency": SaliencyPolicy}[name](seed)


def noisy_copy(model: ObjectModel, noise_mm: float = 1.0, seed: int = 0, *, name: str | None = None) -> ObjectModel:
    """A stand-in for the camera's view: ``model`` with every vertex moved along its normal by N(0, noise_mm)
    mm (seeded), same frame and triangles, no label (a robot's camera does not know the class).

    Raises:
        InvalidArgumentError: a negative or non-finite noise, or a bad seed.
    """
    if isinstance(noise_mm, bool) or not np.isfinite(noise_mm) or noise_mm < 0:
        raise InvalidArgumentError(f"noisy_copy: noise_mm must be a finite number >= 0, got {noise_mm!r}")
    rng = np.random.default_rng(_check_seed(seed))
    shift = rng.normal(0.0, float(noise_mm), model.n_vertices)[:, None] * model.vertex_normals
    return ObjectModel(model.vertices + shift, model.triangles, name=name or f"{model.name}@visual", label=None)


__all__ = ["POLICIES", "ActiveState", "InformationPolicy", "Policy", "RandomPolicy", "SaliencyPolicy",
           "information_gain", "make_policy", "noisy_copy", "same_plane", "visual_key"]
