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
- ``"information"``: planning on simulated touches. ``candidates`` blind planes of the visual model are touched
  *there* (simulated with :func:`tactile.touch` on the visual model after Taubin smoothing, :func:`smoothed`: the
  pad reads tenths of a millimetre and a raw noisy surface reads as noise; ``variants`` times, once as planned and
  then with pose jitter of ``jitter_mm``) and classified, once per visual model and cached. What the robot
  believes the object is (:func:`visual_belief`) is those simulated outcomes pooled (worth ``visual_weight``
  touches) times the real touches so far (log rule). Each step picks the untouched candidate whose simulated
  outcome, fused with the real touches, is expected to give the true class the most probability under that
  belief (:func:`plan_scores`): first the contour that best confirms the camera's view; once real touches
  disagree with it, the one that best lifts the classes still believed in. (The first version maximised the
  expected KL move of the posterior, :func:`information_gain`, on the unsmoothed model: its first pick, the
  contour read most confidently on a noisy surface, was 11 points worse than a random one.)
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from fusion.decide import PROBA_FLOOR, fuse_touches
from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import ObjectModel
from perception.limits import check_count
from perception.validate import check_length
from tactile import sampling
from tactile.contours import Plane
from tactile.explore import SequenceBatch, TactileSequence
from tactile.sensor import FSRSensor
from tactile.touching import MAX_JITTER_MM, Toucher, touch_variants

log = logging.getLogger(__name__)

#: Most vertex noise (mm, standard deviation) of :func:`noisy_copy`: a depth camera errs by millimetres, and objects
#: load 150 mm across; beyond a metre the copy is no view of the object at all.
MAX_NOISE_MM = 1000.0
#: Taubin steps the information policy smooths its visual model with before simulating touches (:func:`smoothed`).
SMOOTH_ITERATIONS = 10


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


def _log(p) -> np.ndarray:
    return np.log(np.maximum(np.asarray(p, dtype=np.float64), PROBA_FLOOR))


def visual_belief(probabilities, outcomes, visual_weight: float = 1.0) -> np.ndarray:
    """(C,) what the robot believes the object is: the touches so far (log rule) times the visual evidence, the
    simulated outcomes of every candidate (M, V, C) pooled by their geometric mean and worth ``visual_weight``
    touches (they are touches of one object, far from independent)."""
    log_b = visual_weight * _log(outcomes).reshape(-1, np.shape(outcomes)[-1]).mean(axis=0)
    if len(probabilities):
        log_b = log_b + _log(probabilities).sum(axis=0)
    log_b -= log_b.max()
    b = np.exp(log_b)
    return b / b.sum()


def plan_scores(probabilities, outcomes, touched=None, *, visual_weight: float = 1.0) -> np.ndarray:
    """(M,) the expected probability that the decision after touching each candidate gives the true class:
    E_{c ~ b}[p'_m(c)] = b . p'_m, where b is :func:`visual_belief` (the camera's view and the touches so far)
    and p'_m the log-rule posterior of the touches so far (``probabilities``, (K, C)) and candidate m's simulated
    outcome (``outcomes`` (M, V, C), averaged over the V variants). With nothing touched it picks the contour whose
    reading best confirms what the camera's view suggests; once real touches disagree with the view, the belief
    moves and so does the choice (the contour that best lifts the classes still believed in). ``touched`` (M,)
    bool: those score -inf.

    Raises:
        InvalidArgumentError: shapes that do not match, or negative / non-finite probabilities.
    """
    q = np.asarray(outcomes, dtype=np.float64)
    if q.ndim != 3 or q.shape[0] < 1 or q.shape[-1] < 1:
        raise InvalidArgumentError(f"plan_scores: outcomes must be (M, V, C), got {q.shape}")
    probs = np.asarray(probabilities, dtype=np.float64)
    if probs.size and (probs.ndim != 2 or probs.shape[1] != q.shape[-1]):
        raise InvalidArgumentError(f"plan_scores: probabilities must be (K, {q.shape[-1]}), got {probs.shape}")
    probs = probs.reshape(-1, q.shape[-1])
    if not (np.isfinite(q).all() and np.isfinite(probs).all()) or (q < 0).any() or (probs < 0).any():
        raise InvalidArgumentError("plan_scores: probabilities must be finite and non-negative")
    belief = visual_belief(probs, q, visual_weight)
    log_p = _log(probs).sum(axis=0) if len(probs) else np.zeros(q.shape[-1])
    new = log_p + _log(q)
    new = np.exp(new - new.max(axis=-1, keepdims=True))
    new /= new.sum(axis=-1, keepdims=True)
    scores = (new @ belief).mean(axis=1)
    if touched is not None:
        scores = np.where(np.asarray(touched, dtype=bool), -np.inf, scores)
    return scores


def visual_key(model: ObjectModel) -> str:
    """A digest of the visual model's geometry (vertices and triangles): what the per-model caches key on."""
    return hashlib.sha256(model.vertices.tobytes() + model.triangles.tobytes()).hexdigest()[:16]


def same_plane(a: Plane, b: Plane) -> bool:
    """Whether two planes are the same (same point, normal equal up to sign)."""
    return bool(np.allclose(a.point, b.point, atol=1e-9) and abs(abs(float(a.normal @ b.normal)) - 1.0) < 1e-12)


def _same_as_any(plane: Plane, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,) :func:`same_plane` of ``plane`` and each of N planes given as (N, 3) points and normals, in one pass."""
    close = np.all(np.abs(plane.point - points) <= 1e-9 + 1e-5 * np.abs(points), axis=1)  # np.allclose's test
    return close & (np.abs(np.abs(normals @ plane.normal) - 1.0) < 1e-12)


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
    #: A precomputed saliency of the visual model (guided policies), else None (computed per visual model).
    saliency = None

    def __init__(self, seed: int = 0, *, cache_size: int = 8) -> None:
        self.seed = _check_seed(seed)
        if isinstance(cache_size, bool) or not isinstance(cache_size, (int, np.integer)) or cache_size < 1:
            raise InvalidArgumentError(f"{self.name} policy: cache_size must be an integer >= 1, got {cache_size!r}")
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
                                                           saliency=self.saliency, saliency_seed=self.seed)}
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
        if toucher.guided:  # the guided strategy's pairs without repeats, in the order seeded by (seed, visual model)
            order = entry.get("order")
            if order is None:
                order = entry["order"] = toucher.pair_order(int(self._rng(entry, 2**31 + 1).integers(2**63)))
            untouched = (order[k] for k in range(len(order)) if not any(same_plane(order[k], p) for p in state.planes))
            return next(untouched, order[len(state.planes)])  # every pair touched: the next cycle
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
    """The paper's: a plane through the visual model's centre and two of its multiview interest points, the pairs
    taken in a seeded order without repeats (:meth:`tactile.touching.Toucher.pair_order`), skipping planes touched.

    Args:
        seed: seeds the pair order and, unless ``saliency`` is given, the view sphere of the saliency.
        saliency: the visual model's multiview :class:`~perception.saliency.Saliency`, computed once where the
            camera's view is processed (a robot looks once, whatever it then touches), in this process and of the
            very :class:`~perception.geometry.ObjectModel` the states hold (a copy, even an equal one, is another
            object); None: computed here, once per visual model.

    Raises:
        InvalidArgumentError: ``saliency`` is not a Saliency, or a bad seed or cache size.
        SaliencyError: (at the first proposal) ``saliency`` is not the multiview saliency of the visual model.
    """

    name, strategy = "saliency", "guided"

    def __init__(self, seed: int = 0, *, saliency=None, cache_size: int = 8) -> None:
        from perception.saliency import Saliency

        super().__init__(seed, cache_size=cache_size)
        if saliency is not None and not isinstance(saliency, Saliency):
            raise InvalidArgumentError(f"saliency policy: saliency must be a perception.saliency.Saliency of the "
                                       f"visual model or None, got {type(saliency).__name__}")
        self.saliency = saliency


class InformationPolicy(Policy):
    """Expected information gain over ``candidates`` simulated contours (see the module docstring).

    Args:
        candidates: planes simulated per visual model (the candidate budget).
        variants: simulated touches per candidate (the first as planned, the others with ``jitter_mm``).
        jitter_mm: pose jitter of the extra variants, mm.
    """

    name, strategy = "information", "blind"

    def __init__(self, seed: int = 0, *, candidates: int = 24, variants: int = 2, jitter_mm: float = 1.0,
                 smooth_iterations: int = SMOOTH_ITERATIONS, visual_weight: float = 1.0, cache_size: int = 8) -> None:
        super().__init__(seed, cache_size=cache_size)
        for label, value, low in (("candidates", candidates, 1), ("variants", variants, 1),
                                  ("smooth_iterations", smooth_iterations, 0)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise InvalidArgumentError(f"information policy: {label} must be an integer >= {low}, got {value!r}")
        jitter_mm = check_length(jitter_mm, "jitter_mm", "information policy", maximum=MAX_JITTER_MM)
        self.candidates, self.variants, self.jitter_mm = int(candidates), int(variants), jitter_mm
        # simulated touches per visual model, refused here rather than after minutes of drawing planes
        check_count("contours", self.candidates * self.variants,
                    f"information policy: {self.candidates} candidates x {self.variants} variants")
        self.smooth_iterations = int(smooth_iterations)
        self.visual_weight = check_length(visual_weight, "visual_weight", "information policy", unit="")
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
        planes = self.candidate_planes(state)
        outcomes = simulated_outcomes(state.classifier, self.simulated_touches(state, planes))
        entry["outcomes"] = (state.classifier, outcomes)  # the planes are cached by candidate_planes
        self.simulation_seconds.append(time.perf_counter() - start)
        return planes, outcomes

    def candidate_planes(self, state: ActiveState) -> list[Plane]:
        """The ``candidates`` distinct blind planes of the visual model, drawn with the policy's seed and the model's
        geometry (the same planes whatever the classifier)."""
        entry = self._entry(state)
        cached = entry.get("planes")
        if cached is not None:
            return cached
        toucher, surface = entry["toucher"], self._surface(state)
        rng = np.random.default_rng([self.seed, int(entry["key"][:16], 16) % 2**32, 2**31])
        planes: list[Plane] = []
        points, normals = np.empty((self.candidates, 3)), np.empty((self.candidates, 3))  # of the planes so far
        for _ in range(self.candidates * sampling.MAX_DRAWS):
            if len(planes) == self.candidates:
                break
            plane = toucher.draw(rng, cut_by=surface).plane  # drawn on the visual model, cut where it is pressed
            if not _same_as_any(plane, points[:len(planes)], normals[:len(planes)]).any():
                points[len(planes)], normals[len(planes)] = plane.point, plane.normal
                planes.append(plane)
        if not planes:
            raise ContourError(f"{state.visual.name}: no candidate plane cuts the visual model")
        entry["planes"] = planes
        return planes

    def _surface(self, state: ActiveState) -> Toucher:
        """The Toucher of the smoothed visual model (made once per visual model): it cuts the candidate planes."""
        entry = self._entry(state)
        if "surface" not in entry:
            entry["surface"] = Toucher(smoothed(state.visual, self.smooth_iterations), "blind", probes=state.probes)
        return entry["surface"]

    def simulated_touches(self, state: ActiveState, planes: list[Plane]) -> list[list[TactileSequence]]:
        """The touches of ``planes`` on the smoothed visual model, one list per variant (the first as planned, the
        others jittered by ``jitter_mm``): the planes cut once, every variant pressed in one pass."""
        return touch_variants(self._surface(state), planes, state.sensor(),
                              [(self.seed + v, self.jitter_mm if v else 0.0) for v in range(self.variants)])

    def scores(self, state: ActiveState) -> np.ndarray:
        """(M,) each candidate's score under the current state (:func:`plan_scores`); touched candidates score
        -inf."""
        planes, outcomes = self.simulated(state)
        touched = np.zeros(len(planes), dtype=bool)
        if state.planes:
            points = np.array([p.point for p in state.planes])
            normals = np.array([p.normal for p in state.planes])
            touched = np.array([_same_as_any(c, points, normals).any() for c in planes])
        return plan_scores(state.probabilities, outcomes, touched, visual_weight=self.visual_weight)

    def _propose(self, state: ActiveState) -> Plane:
        planes, outcomes = self.simulated(state)
        scores = self.scores(state)
        if not np.isfinite(scores).any():  # every candidate touched: touch the best again
            scores = plan_scores(state.probabilities, outcomes, np.zeros(len(planes), dtype=bool),
                                 visual_weight=self.visual_weight)
        return planes[int(np.argmax(scores))]


def simulated_outcomes(classifier, variants: list[list[TactileSequence]]) -> np.ndarray:
    """(M, V, C) ``classifier``'s probabilities of V variants of M simulated touches (:meth:`InformationPolicy.
    simulated_touches`), classified variant by variant: a classifier's arithmetic may depend on the batch (BLAS picks
    its kernels by the matrix shapes), and a last bit moved can change which near-tied candidate is chosen."""
    classes = [str(c) for c in classifier.classes_]
    spec = classifier.sensor().spec()
    return np.stack([np.asarray(classifier.predict_proba(SequenceBatch.from_sequences(
        sequences, class_names=classes, sensor_spec=spec)), dtype=np.float64) for sequences in variants], axis=1)


def smoothed(model: ObjectModel, iterations: int) -> ObjectModel:
    """``model`` after ``iterations`` steps of Taubin smoothing (no shrinking; same triangles and frame), 0: as is.

    A camera's mesh is denoised before anything reads its surface: the FSR pad reads tenths of a millimetre, and
    touches simulated on a raw noisy surface read the noise (on the 1 mm noisy copies of the experiments the
    classifier's simulated answer agreed with the real touch's on 40 % of the contours; after 10 steps, on
    most).
    """
    if iterations <= 0:
        return model
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(model.vertices),
                                     o3d.utility.Vector3iVector(model.triangles))
    mesh = mesh.filter_smooth_taubin(number_of_iterations=int(iterations))
    return ObjectModel(np.asarray(mesh.vertices), model.triangles, name=f"{model.name}@smoothed", label=None)


#: Each policy class by its name; :data:`POLICIES` lists the names in this order.
_BY_NAME = {policy.name: policy for policy in (RandomPolicy, SaliencyPolicy, InformationPolicy)}
POLICIES = tuple(_BY_NAME)


def make_policy(name: str, seed: int = 0, **options) -> Policy:
    """A new policy by name (:data:`POLICIES`); ``options`` are its class's keyword arguments (:class:`RandomPolicy`,
    :class:`SaliencyPolicy`, :class:`InformationPolicy`).

    Raises:
        InvalidArgumentError: unknown name, an option the policy does not take, or a bad value of one it takes.
    """
    if not isinstance(name, str) or name not in POLICIES:
        raise InvalidArgumentError(f"unknown touch policy {name!r}; choose one of {', '.join(POLICIES)}")
    policy = _BY_NAME[name]
    takes = [p.name for p in inspect.signature(policy).parameters.values() if p.kind is p.KEYWORD_ONLY]
    unknown = sorted(set(options) - set(takes))
    if unknown:
        raise InvalidArgumentError(f"the {name} policy takes {', '.join(takes)}; got {', '.join(unknown)}")
    return policy(seed, **options)


def noisy_copy(model: ObjectModel, noise_mm: float = 1.0, seed: int = 0, *, name: str | None = None) -> ObjectModel:
    """A stand-in for the camera's view: ``model`` with every vertex moved along its normal by N(0, noise_mm)
    mm (seeded), same frame and triangles, no label (a robot's camera does not know the class).

    Raises:
        InvalidArgumentError: a noise that is negative, not finite or above ``MAX_NOISE_MM``, or a bad seed.
    """
    noise_mm = check_length(noise_mm, "noise_mm", "noisy_copy", maximum=MAX_NOISE_MM)
    rng = np.random.default_rng(_check_seed(seed))
    shift = rng.normal(0.0, float(noise_mm), model.n_vertices)[:, None] * model.vertex_normals
    return ObjectModel(model.vertices + shift, model.triangles, name=name or f"{model.name}@visual", label=None)


__all__ = ["MAX_NOISE_MM", "POLICIES", "SMOOTH_ITERATIONS", "ActiveState", "InformationPolicy", "Policy", "RandomPolicy",
           "SaliencyPolicy", "information_gain", "make_policy", "noisy_copy", "plan_scores", "same_plane",
           "simulated_outcomes", "smoothed", "visual_belief", "visual_key"]
