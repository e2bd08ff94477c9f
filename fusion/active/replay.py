"""Next-touch criteria screened offline: one object's candidate contours banked once, any criterion replayed in
milliseconds.

The information policy chooses, step by step, among the same M candidate planes of the visual model
(:meth:`~fusion.active.InformationPolicy.candidate_planes`). With a noise-free sensor the real reading of a plane on
the true object does not depend on when it is touched, so a :class:`CandidateBank` (the candidates, their simulated
outcomes on the visual model and their real readings on the true object, each read by one or more classifiers)
holds everything an episode over those candidates can see. :func:`replay` then runs a criterion over it and gives
the decisions of :func:`~fusion.active.run_episode` with that policy, bit for bit (tested): a planner can be tried
with another classifier, or another rule, without touching anything again.

The bank holds real readings that no policy may read before touching. :func:`replay` hands a criterion only the
simulated outcomes and the readings of the planes touched so far (:class:`ReplayView`); the label is not in the bank.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fusion.active.episode import touch_seed
from fusion.active.policies import ActiveState, InformationPolicy, plan_scores, simulated_outcomes
from fusion.decide import PROBA_FLOOR, fuse_touches
from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import ObjectModel
from perception.limits import check_count
from perception.validate import check_length
from tactile.contours import Plane
from tactile.explore import SequenceBatch
from tactile.touching import touch


@dataclass(frozen=True)
class CandidateBank:
    """One object's candidates as an information policy of one seed draws them.

    Attributes:
        object: the true object's name.
        classes: the classifiers' class names (columns of the arrays).
        planes: the M candidate planes (through the visual model's centre, mm).
        simulated: {classifier name: (M, V, C) probabilities of the V simulated variants of each candidate}.
        real: {classifier name: (M, C) probabilities of each candidate touched on the true object}; uniform where the
            plane missed it (as :func:`~fusion.active.run_episode` counts a miss).
        missed: (M,) bool, the planes that missed the true object.

    Raises:
        InvalidArgumentError: no planes, no classes, arrays whose shapes do not match, or probabilities that are not
            finite and non-negative (a bank made by hand is checked as one :func:`build_bank` makes).
    """

    object: str
    classes: list[str]
    planes: list[Plane]
    simulated: dict[str, np.ndarray]
    real: dict[str, np.ndarray]
    missed: np.ndarray

    def __post_init__(self) -> None:
        m, c = len(self.planes), len(self.classes)
        where = f"CandidateBank of {self.object!r}"
        if not m or not c:
            raise InvalidArgumentError(f"{where}: needs at least one plane and one class, got {m} and {c}")
        if not isinstance(self.simulated, dict) or not isinstance(self.real, dict) or set(self.simulated) != set(self.real):
            raise InvalidArgumentError(f"{where}: simulated and real must be dicts over the same classifier names")
        for name in self.real:
            sim, real = np.asarray(self.simulated[name]), np.asarray(self.real[name])
            if sim.ndim != 3 or sim.shape[0] != m or sim.shape[2] != c or real.shape != (m, c):
                raise InvalidArgumentError(f"{where}: classifier {name!r} has simulated {sim.shape} and real {real.shape},"
                                           f" expected (M, V, C) and (M, C) with M = {m}, C = {c}")
            for values in (sim, real):
                if values.dtype.kind not in "biuf" or not np.isfinite(values).all() or (values < 0).any():
                    raise InvalidArgumentError(f"{where}: classifier {name!r} has probabilities that are not finite and "
                                               "non-negative")
        if np.shape(self.missed) != (m,):
            raise InvalidArgumentError(f"{where}: missed must be ({m},), got {np.shape(self.missed)}")


@dataclass(frozen=True)
class ReplayView:
    """What a criterion may read at one step of a replay: nothing about an untouched plane but its simulation.

    Attributes:
        simulated: {classifier name: (M, V, C)} as in the bank.
        readings: {classifier name: (K, C) the real readings of the K planes touched so far, in touch order}.
        touched: (M,) bool, the candidates touched so far.
        step: K, the touches made so far.
    """

    simulated: dict[str, np.ndarray]
    readings: dict[str, np.ndarray]
    touched: np.ndarray
    step: int


#: A criterion: (M,) scores of the candidates at one step; the highest untouched one is touched next.
Criterion = Callable[[ReplayView], np.ndarray]


def _sensor_and_probes(classifiers: dict):
    if not isinstance(classifiers, dict) or not classifiers:
        raise InvalidArgumentError(f"build_bank: classifiers must be a non-empty {{name: fitted classifier}} dict, got "
                                   f"{type(classifiers).__name__}")
    for name, model in classifiers.items():
        if not all(hasattr(model, a) for a in ("classes_", "probes", "sensor", "predict_proba")):
            raise InvalidArgumentError(f"build_bank: classifier {name!r} is not a fitted classifier (classes_, probes, "
                                       f"sensor(), predict_proba), got {type(model).__name__}")
    first = next(iter(classifiers.values()))
    classes = [str(c) for c in first.classes_]
    spec, probes = first.sensor().spec(), int(first.probes)
    for name, model in classifiers.items():
        if [str(c) for c in model.classes_] != classes:
            raise InvalidArgumentError(f"build_bank: classifier {name!r} has classes {list(model.classes_)}, the first "
                                       f"one {classes}: the bank needs one class order")
        if model.sensor().spec() != spec or int(model.probes) != probes:
            raise InvalidArgumentError(f"build_bank: classifier {name!r} reads another sensor or probe count than the "
                                       "first one")
    sensor = first.sensor()
    if sensor.noise_std != 0 or sensor.dead_taxel_rate != 0:
        raise InvalidArgumentError("build_bank: the sensor has taxel noise or dead taxels, so a plane's reading depends "
                                   "on the step it is touched at and a replay would not be the episode; bank with a "
                                   "noise-free sensor")
    return first, classes, sensor, probes


def build_bank(true_model: ObjectModel, visual: ObjectModel, classifiers: dict, policy: InformationPolicy) -> CandidateBank:
    """Bank ``policy``'s candidates of ``visual`` (the camera's model) for ``true_model``: simulated on the visual model
    and touched on the true one, read by every classifier of ``classifiers`` ({name: fitted classifier}; one class
    order, sensor and probe count, the sensor noise-free). Each real touch is classified on its own, as an episode
    classifies it.

    Raises:
        InvalidArgumentError: an empty or mismatched ``classifiers``, one that is not a fitted classifier or gives
            probabilities that are not finite, non-negative and of its class count, a noisy sensor, a policy that is
            not an :class:`~fusion.active.InformationPolicy`.
        ContourError: no candidate plane cuts the visual model.
    """
    if not isinstance(policy, InformationPolicy):
        raise InvalidArgumentError(f"build_bank: needs an InformationPolicy (its candidates), got "
                                   f"{type(policy).__name__}")
    first, classes, sensor, probes = _sensor_and_probes(classifiers)
    state = ActiveState(visual, first)
    planes = policy.candidate_planes(state)
    variants = policy.simulated_touches(state, planes)
    simulated = {name: simulated_outcomes(model, variants) for name, model in classifiers.items()}  # checked by the bank
    real = {name: np.full((len(planes), len(classes)), 1.0 / len(classes)) for name in classifiers}
    missed = np.zeros(len(planes), dtype=bool)
    for m, plane in enumerate(planes):
        try:  # the seed of an episode's first touch: a noise-free read-out does not use it
            sequence = touch(true_model, "blind", 1, sensor, probes, seed=touch_seed(0, 0), planes=[plane])[0]
        except ContourError:
            missed[m] = True
            continue
        sequence.strategy, sequence.label = policy.name, None  # as an episode: the robot does not know the class
        batch = SequenceBatch.from_sequences([sequence], class_names=classes, sensor_spec=sensor.spec())
        for name, model in classifiers.items():
            real[name][m] = _checked(model.predict_proba(batch), (1, len(classes)), name)[0]
    return CandidateBank(true_model.name, classes, planes, simulated, real, missed)


def _checked(proba, shape: tuple, name) -> np.ndarray:
    proba = np.asarray(proba, dtype=np.float64)
    if proba.shape != shape or not np.isfinite(proba).all() or (proba < 0).any():
        raise InvalidArgumentError(f"build_bank: classifier {name!r} gave probabilities of shape {proba.shape} (expected "
                                   f"{shape}, finite and non-negative)")
    return proba


def information_criterion(planner: str, visual_weight: float = 1.0) -> Criterion:
    """The information policy's rule (:func:`~fusion.active.plan_scores`) with the classifier named ``planner``'s
    simulated outcomes and real readings; the classifier that decides may be another one (:func:`replay`).

    Raises:
        InvalidArgumentError: a planner that is not a name, a negative or non-finite ``visual_weight``; when scoring, a
            planner the bank does not hold.
    """
    if not isinstance(planner, str):
        raise InvalidArgumentError(f"information_criterion: planner must be a classifier name, got {planner!r}")
    visual_weight = check_length(visual_weight, "visual_weight", "information_criterion", unit="")

    def scores(view: ReplayView) -> np.ndarray:
        if planner not in view.simulated:
            raise InvalidArgumentError(f"information_criterion: no classifier {planner!r} in the bank "
                                       f"(it holds {sorted(view.simulated)})")
        return plan_scores(view.readings[planner], view.simulated[planner], view.touched, visual_weight=visual_weight)

    return scores


def replay(bank: CandidateBank, criterion: Criterion, decide: str, max_touches: int = 8) -> tuple[list[int], np.ndarray]:
    """Run ``criterion`` over ``bank`` for ``max_touches`` steps: each step touches the untouched candidate it scores
    highest (the first of ties; once every candidate is touched, the best again, as the information policy does);
    the classifier named ``decide`` reads the touches, fused by the log rule.

    Returns:
        the candidates touched, in order, and (max_touches, C) the posterior after each touch.

    Raises:
        InvalidArgumentError: not a bank with planes, a criterion that is not callable, an unknown classifier name, a
            budget below 1 or above the touch limit (:func:`perception.limits.check_count`), scores that are not (M,)
            real numbers without NaN (+inf is the highest score, -inf never chosen while another candidate is not).
    """
    _check_episode("replay", bank, decide, max_touches)
    if not callable(criterion):
        raise InvalidArgumentError(f"replay: criterion must be callable, got {type(criterion).__name__}")
    n = len(bank.planes)
    simulated = {name: _read_only(values) for name, values in bank.simulated.items()}  # a criterion cannot edit the bank
    touched, order, posteriors = np.zeros(n, dtype=bool), [], []
    for step in range(int(max_touches)):
        readings = {name: values[order] for name, values in bank.real.items()}
        scores = np.where(touched, -np.inf, _scores(criterion, ReplayView(simulated, readings, touched.copy(),
                                                                           step), n))
        if not (scores > -np.inf).any():  # every candidate touched (or scored -inf): the best again
            scores = _scores(criterion, ReplayView(simulated, readings, np.zeros(n, dtype=bool), step), n)
        choice = int(np.argmax(scores))
        order.append(choice)
        touched[choice] = True
        posteriors.append(fuse_touches(bank.real[decide][order], rule="log"))
    return order, np.asarray(posteriors)


def hindsight(bank: CandidateBank, decide: str, max_touches: int = 8) -> tuple[list[int], np.ndarray]:
    """Not a policy: what the classifier ``decide`` would say with every candidate touched, reached in as few touches
    as a choice can. It reads every candidate's real reading (which no policy may), takes the class that all of them
    fused by the log rule name (the pooled verdict) and touches the candidates in the order of their reading's margin
    for that class (its log-probability minus the highest of another class), the widest first, ties by index; past the
    last candidate, the first again (as :func:`replay` does). With two classes the first K of that order name the
    pooled verdict whenever any K candidates do (barring an exact tie of the pooled scores, which float summation in
    another order may break the other way); with more classes it is greedy.

    A reference, not a bound: a rule that knew every reading but not the label would decide as the pooled verdict, so
    where that verdict is wrong this is wrong at every K, where a random choice is sometimes right.

    Returns:
        the candidates in that order, and (max_touches, C) the posterior after each touch (as :func:`replay`).

    Raises:
        InvalidArgumentError: as :func:`replay` for the bank, ``decide`` and ``max_touches``.
    """
    _check_episode("hindsight", bank, decide, max_touches)
    real = np.asarray(bank.real[decide], dtype=np.float64)
    verdict = int(np.argmax(fuse_touches(real, rule="log")))
    log_p = np.log(np.maximum(real, PROBA_FLOOR))  # the floor the log rule reads with
    margin = log_p[:, verdict] - np.delete(log_p, verdict, axis=1).max(axis=1, initial=-np.inf)
    ranked = np.argsort(-margin, kind="stable").tolist()
    order = [ranked[k] if k < len(ranked) else ranked[0] for k in range(int(max_touches))]
    posteriors = [fuse_touches(real[order[: k + 1]], rule="log") for k in range(len(order))]
    return order, np.asarray(posteriors)


def _check_episode(where: str, bank, decide, max_touches) -> None:
    """What :func:`replay` and :func:`hindsight` refuse alike: no bank, an unknown decider, a bad touch budget."""
    if not isinstance(bank, CandidateBank) or not bank.planes:
        raise InvalidArgumentError(f"{where}: needs a CandidateBank with at least one plane, got {type(bank).__name__}")
    if not isinstance(decide, str) or decide not in bank.real:
        raise InvalidArgumentError(f"{where}: no classifier {decide!r} in the bank of {bank.object} "
                                   f"(it holds {sorted(bank.real)})")
    if isinstance(max_touches, bool) or not isinstance(max_touches, (int, np.integer)) or max_touches < 1:
        raise InvalidArgumentError(f"{where}: max_touches must be an integer >= 1, got {max_touches!r}")
    check_count("touches", max_touches, f"{where}: max_touches")  # a bound: each step allocates and the loop is O(K^2)


def _scores(criterion: Criterion, view: ReplayView, n: int) -> np.ndarray:
    raw = np.asarray(criterion(view))
    if raw.dtype.kind not in "biuf" or raw.shape != (n,) or np.isnan(raw.astype(np.float64)).any():
        raise InvalidArgumentError(f"replay: a criterion must give ({n},) real scores without NaN, got {raw.dtype} "
                                   f"shape {raw.shape}")
    return raw.astype(np.float64)


def _read_only(values: np.ndarray) -> np.ndarray:
    view = np.asarray(values).view()
    view.flags.writeable = False
    return view


__all__ = ["CandidateBank", "Criterion", "ReplayView", "build_bank", "hindsight", "information_criterion", "replay"]
