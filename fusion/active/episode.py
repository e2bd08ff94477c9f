"""Sequential decisions: touch, classify, fuse (log rule), and stop at a confidence threshold or a touch budget.

:func:`run_episode` is the one place the true object and the plan meet: the policy proposes a plane from the
:class:`~fusion.active.policies.ActiveState` (visual model, touches so far, classifier), the plane is touched on
the **true** object with :func:`tactile.touch`, the classifier reads the sequence, the posterior is updated and
the loop stops when its largest probability reaches ``threshold`` or ``max_touches`` are spent. The label of
the true object is never read.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from fusion.active.policies import ActiveState, Policy
from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import ObjectModel
from tactile.contours import Plane
from tactile.explore import SequenceBatch
from tactile.touching import touch

log = logging.getLogger(__name__)


@dataclass
class Episode:
    """One sequential decision.

    Attributes:
        decision: the class with the largest fused probability after the last touch.
        touches: touches used (<= the budget; fewer when the threshold stopped it).
        classes: the classifier's class names (columns of the arrays below).
        posteriors: (touches, C) fused posterior after each touch.
        probabilities: (touches, C) the classifier's output for each touch alone.
        planes: the touched planes, in order.
        missed: (touches,) whether a plane missed the true object (its touch told nothing: uniform output).
        planning_s, touching_s, classifying_s: (touches,) wall seconds of each step's parts.
        policy: the policy's name.
    """

    decision: str
    touches: int
    classes: list[str]
    posteriors: np.ndarray
    probabilities: np.ndarray
    planes: list[Plane] = field(default_factory=list)
    missed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    planning_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    touching_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    classifying_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    policy: str = ""

    def decisions(self) -> list[str]:
        """The decision after each touch."""
        return [self.classes[int(i)] for i in np.argmax(self.posteriors, axis=1)]

    def step_seconds(self) -> np.ndarray:
        """(touches,) wall seconds per decision step (planning + touching + classifying)."""
        return self.planning_s + self.touching_s + self.classifying_s


def touch_seed(seed: int, step: int) -> int:
    """The sensor-noise seed of touch ``step`` of an episode seeded ``seed``."""
    return int(np.random.default_rng([int(seed), int(step)]).integers(2**31 - 1))


def run_episode(
    true_model: ObjectModel,
    visual: ObjectModel,
    classifier,
    policy: Policy,
    *,
    max_touches: int = 8,
    threshold: float | None = None,
    seed: int = 0,
    jitter_mm: float = 0.0,
) -> Episode:
    """Recognise ``true_model`` by touches that ``policy`` plans on ``visual`` (both in one frame, mm).

    Args:
        true_model: the object touched (its label is not read).
        visual: what the camera saw: a reconstruction or a noisy copy (:func:`~fusion.active.noisy_copy`).
        classifier: a fitted classifier (its sensor and probe count are used for every touch).
        max_touches: the touch budget (>= 1).
        threshold: stop once the fused posterior's largest probability reaches it (None: use the budget).
        seed: seeds the sensor noise of the touches (:func:`touch_seed`).
        jitter_mm: pose jitter of the real touches, mm (the finger lands near the plan).

    Raises:
        InvalidArgumentError: a budget below 1, a threshold outside (0, 1], a bad seed or jitter.
    """
    if isinstance(max_touches, bool) or not isinstance(max_touches, (int, np.integer)) or max_touches < 1:
        raise InvalidArgumentError(f"run_episode: max_touches must be an integer >= 1, got {max_touches!r}")
    if threshold is not None and not (np.isfinite(threshold) and 0 < threshold <= 1):
        raise InvalidArgumentError(f"run_episode: threshold must be in (0, 1] or None, got {threshold!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidArgumentError(f"run_episode: seed must be an integer >= 0, got {seed!r}")
    state = ActiveState(visual, classifier)
    sensor, probes, classes = state.sensor(), state.probes, state.classes
    plan_s, touch_s, class_s, missed, posteriors = [], [], [], [], []
    for step in range(int(max_touches)):
        start = time.perf_counter()
        plane = policy.propose(state)
        planned = time.perf_counter()
        try:
            sequence = touch(true_model, "blind", 1, sensor, probes, seed=touch_seed(seed, step), planes=[plane],
                             jitter_mm=jitter_mm)[0]
            sequence.strategy, sequence.label = policy.name, None  # the robot does not know the class
        except ContourError as exc:  # the plan missed the true object: nothing felt
            log.info("%s: planned plane missed the object (%s)", true_model.name, exc)
            sequence = None
        touched = time.perf_counter()
        if sequence is None:
            proba = np.full(len(classes), 1.0 / len(classes))
        else:
            batch = SequenceBatch.from_sequences([sequence], class_names=classes, sensor_spec=sensor.spec())
            proba = np.asarray(classifier.predict_proba(batch), dtype=np.float64)[0]
        classified = time.perf_counter()
        state.planes.append(plane)
        state.probabilities.append(proba)
        if sequence is not None:
            state.sequences.append(sequence)
        posteriors.append(state.posterior)
        plan_s.append(planned - start)
        touch_s.append(touched - planned)
        class_s.append(classified - touched)
        missed.append(sequence is None)
        if threshold is not None and posteriors[-1].max() >= threshold:
            break
    post = np.asarray(posteriors)
    return Episode(decision=classes[int(np.argmax(post[-1]))], touches=len(post), classes=classes, posteriors=post,
                   probabilities=np.asarray(state.probabilities), planes=list(state.planes),
                   missed=np.asarray(missed, dtype=bool), planning_s=np.asarray(plan_s),
                   touching_s=np.asarray(touch_s), classifying_s=np.asarray(class_s), policy=policy.name)


def stopped(episode: Episode, threshold: float) -> tuple[str, int]:
    """(decision, touches used) had ``episode`` stopped at the first posterior reaching ``threshold`` (the same
    touches: an episode's first k touches do not depend on later ones)."""
    reached = np.flatnonzero(episode.posteriors.max(axis=1) >= threshold)
    k = int(reached[0]) + 1 if len(reached) else episode.touches
    return episode.classes[int(np.argmax(episode.posteriors[k - 1]))], k


__all__ = ["Episode", "run_episode", "stopped", "touch_seed"]
