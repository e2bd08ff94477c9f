"""Touching an object along K contours: the one road every caller takes (datasets, experiments, ``recognize``,
the camera path and touch policies).

:func:`touch` draws contour planes by a sampling strategy (:mod:`tactile.sampling`), cuts them (a plane cut once
per :class:`Toucher`), optionally jitters the probe poses, presses the FSR pad along each contour and returns the
tactile sequences. Two seed schemes define the bytes, and both are kept exactly:

- ``seeding="stream"`` (:func:`explore_object`, dataset stores): one generator from ``seed``; for each contour the
  planes are drawn from it (a plane that misses the object is re-drawn, up to ``MAX_DRAWS`` times), then the
  contour's sensor-noise seed. Guided strategies instead draw one number first, the seed of their pair order
  (:meth:`Toucher.pair_order`: pairs without repeats), and take its positions in turn. Row k of a store is the
  first contour of this scheme seeded with :func:`tactile.dataset.contour_seed` (seed, object, strategy, k);
  guided rows take position k of the object's pair order (:func:`tactile.dataset.pair_order_seed`).
- ``seeding="object"`` (the experiments, ``visuotactile recognize``): three streams spawned from (seed, object
  name, strategy) (:func:`object_seed`): ``n + SPARE_PLANES`` planes drawn at once (those that miss are
  skipped; guided strategies take the first positions of a pair order seeded from that stream), the noise seeds
  indexed by plane, and the pose jitter. Every jitter or noise level touches the same contours.

Pose jitter of level ``j`` mm (:func:`jitter_contour`): each probe's pad centre moves by N(0, j) mm along the
pad's two axes and its normal tilts by N(0, ``TILT_DEG_PER_MM`` * j) degrees about a random axis in the pad
plane; the pad is pressed at that pose, while the sequence records the *planned* pose (the robot does not know
its error).
"""

from __future__ import annotations

import logging
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from perception import saliency as attention
from perception.errors import ContourError, InvalidArgumentError
from perception.geometry import ObjectModel
from perception.limits import check_bytes
from perception.limits import check_count as check_limit
from perception.runtime import progress_bar
from perception.validate import check_count, check_length, check_object_model, check_seed
from tactile import sampling
from tactile.contours import Contour, Plane, make_contour
from tactile.explore import TactileSequence, sequence_nbytes
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: The seed schemes of :func:`touch` (see the module docstring).
SEEDINGS = ("stream", "object")
#: Extra planes drawn per object by the "object" scheme in case some miss (a plane can miss a ring's hole).
SPARE_PLANES = 20
#: Pose jitter: normal tilt std (degrees) per mm of position jitter std.
TILT_DEG_PER_MM = 2.5
#: Most pose jitter (mm, standard deviation): a finger lands millimetres from its plan; beyond a metre it is not
#: touching the object (and far beyond, probe positions overflow).
MAX_JITTER_MM = 1000.0


@dataclass
class TouchTiming:
    """Wall-clock seconds of simulated touching: per contour (cut + press) and per object (saliency)."""

    contour_seconds: list[float] = field(default_factory=list)
    saliency_seconds: list[float] = field(default_factory=list)

    def median_contour(self) -> float:
        return float(np.median(self.contour_seconds)) if self.contour_seconds else 0.0

    def median_saliency(self) -> float:
        return float(np.median(self.saliency_seconds)) if self.saliency_seconds else 0.0


def check_strategy(strategy: str) -> None:
    """Refuse an unknown sampling strategy before anything is loaded or computed (what :func:`touch` checks first;
    callers above tactile check here, through the touching road, not in :mod:`tactile.sampling`).

    Raises:
        InvalidArgumentError: ``strategy`` is not a key of :data:`tactile.sampling.STRATEGIES` (the keys named).
    """
    sampling.check_strategy(strategy)


def _check_jitter(jitter_mm, name: str | None = None) -> float:
    """``jitter_mm`` as a float if it is a finite real number in [0, ``MAX_JITTER_MM``] (mm), refused by ``name``
    otherwise."""
    return check_length(jitter_mm, "pose jitter", name or "jitter_contour", maximum=MAX_JITTER_MM)


def _check_probes(probes, name: str) -> int:
    """``probes`` as an int: an integer >= 2 and within the probes-per-contour limit (:mod:`perception.limits`)."""
    probes = check_count(probes, "probes", name, minimum=2)
    return check_limit("probes", probes, f"{name}: probes")


def _check_planes(planes, name: str) -> list[Plane]:
    """``planes`` as a list if it is an iterable of :class:`~tactile.contours.Plane` (a list, tuple or generator).

    Raises:
        InvalidArgumentError: not iterable, or an item that is not a Plane (None, a (point, normal) pair...).
    """
    try:
        planes = list(planes)
    except TypeError:
        raise InvalidArgumentError(f"{name}: planes must be an iterable of tactile.contours.Plane, got "
                                   f"{type(planes).__name__}") from None
    for k, plane in enumerate(planes):
        if not isinstance(plane, Plane):
            raise InvalidArgumentError(f"{name}: plane {k} must be a tactile.contours.Plane, got "
                                       f"{type(plane).__name__}")
    return planes


def _check_contours(n, name: str) -> int:
    """``n`` as an int: an integer >= 1 and within the contours-per-object limit (:mod:`perception.limits`)."""
    n = check_count(n, "n_contours", name)
    return check_limit("contours", n, f"{name}: n_contours")


def object_seed(seed: int, name: str, strategy: str) -> np.random.SeedSequence:
    """The seed sequence of one object's contours in the "object" scheme: (seed, object name, strategy) only."""
    return np.random.SeedSequence([int(seed), zlib.crc32(name.encode()), zlib.crc32(strategy.encode())])


def jitter_contour(contour: Contour, position_mm: float, rng: np.random.Generator) -> Contour:
    """``contour`` with each probe moved by N(0, position_mm) along the pad axes and its normal tilted by
    N(0, TILT_DEG_PER_MM * position_mm) degrees (see the module docstring); position_mm 0 returns it as is
    (and draws nothing from ``rng``).

    Raises:
        InvalidArgumentError: position_mm negative or not finite.
    """
    position_mm = _check_jitter(position_mm)
    if position_mm == 0:
        return contour
    n = contour.n_probes
    t, b, normal = contour.tangents, contour.binormals, contour.normals
    shift = rng.normal(0.0, position_mm, (n, 2))
    positions = contour.positions + shift[:, :1] * t + shift[:, 1:] * b
    angle = np.radians(rng.normal(0.0, TILT_DEG_PER_MM * position_mm, n))[:, None]
    phi = rng.uniform(0.0, 2 * np.pi, n)[:, None]
    axis = np.cos(phi) * t + np.sin(phi) * b  # unit, in the pad plane
    normals = np.cos(angle) * normal + np.sin(angle) * axis
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tangents = t - np.sum(t * normals, axis=1, keepdims=True) * normals
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    return Contour(contour.plane, contour.polyline, contour.closed, positions, normals, tangents,
                   contour.triangle_ids)


@dataclass(frozen=True)
class Planned:
    """One contour to touch and the integer seed of its sensor noise."""

    contour: Contour
    noise_seed: int


class Toucher:
    """One object touched by one strategy: its candidate points found once, each plane cut once.

    Guided strategies take the pairs of their ``INTEREST_POOL`` interest points without repeats
    (:meth:`pair_order`: the pairs whose plane cuts the object, each once before any again); a plane asked for
    again is cut once and gives the same :class:`~tactile.contours.Contour` object.

    Args:
        model: the object.
        strategy: a key of :data:`tactile.sampling.STRATEGIES`.
        probes: probes per contour (>= 2).
        saliency: a precomputed :class:`~perception.saliency.Saliency` of the strategy's method, to reuse;
            else computed here with ``saliency_seed`` (and timed into ``timing``).

    Raises:
        InvalidArgumentError: ``model`` not an ObjectModel, unknown strategy, probes not an integer >= 2 or above
            the probe limit (:mod:`perception.limits`). ContourError: a flat object.
        SaliencyError: ``saliency`` is of another method or object.
    """

    def __init__(
        self,
        model: ObjectModel,
        strategy: str = "guided",
        *,
        probes: int = 25,
        saliency: attention.Saliency | None = None,
        saliency_seed: int = 0,
        timing: TouchTiming | None = None,
    ) -> None:
        check_object_model(model, "Toucher")
        sampling.check_strategy(strategy)
        self.model, self.strategy = model, strategy
        self.probes = _check_probes(probes, model.name)
        sampling.check_not_flat(model)
        method = sampling.STRATEGIES[strategy]
        if method is not None and saliency is None:
            start = time.perf_counter()
            saliency = attention.saliency(model, method, seed=saliency_seed)
            if timing is not None:
                timing.saliency_seconds.append(time.perf_counter() - start)
        self.saliency = saliency
        self.points = sampling.candidates(model, strategy, saliency)
        self._cuts: dict[tuple[bytes, bytes], Contour | ContourError] = {}
        self._pairs: list[Plane] | None = None
        self._last_order: sampling.PairOrder | None = None

    @property
    def guided(self) -> bool:
        """Whether the strategy draws from interest points (:func:`tactile.sampling.is_guided`)."""
        return sampling.is_guided(self.strategy)

    def pair_order(self, seed: int) -> sampling.PairOrder:
        """The pairs of interest points whose plane cuts the object, in the seeded order of
        :class:`~tactile.sampling.PairOrder` (cut once per Toucher; guided strategies only).

        Raises:
            ContourError: no pair gives a plane that cuts the object.
            InvalidArgumentError: a blind strategy (its candidates are every vertex: pairs are drawn, not listed).
        """
        if not self.guided:
            raise InvalidArgumentError(f"{self.model.name}: the {self.strategy!r} strategy draws random vertex pairs; "
                                       "only guided strategies have a pair order")
        if self._pairs is None:
            usable = []
            for plane in sampling.pair_planes(self.model, self.points):
                try:
                    self.cut(plane)
                except ContourError as exc:
                    log.debug("%s: leaving out a pair (%s)", self.model.name, exc)
                    continue
                usable.append(plane)
            self._pairs = usable
        last = self._last_order  # kept: a store asks for one position of the same order per row
        if last is None or isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or last.seed != seed:
            last = self._last_order = sampling.PairOrder(self._pairs, seed, self.model.name)
        return last

    def cut(self, plane) -> Contour:
        """The contour of ``plane`` (cut once per plane).

        Raises:
            ContourError: the plane misses the object or cuts a zero-length contour.
        """
        key = (plane.point.tobytes(), plane.normal.tobytes())
        found = self._cuts.get(key)
        if found is None:
            try:
                found = make_contour(self.model, plane, self.probes)
            except ContourError as exc:
                found = exc
            self._cuts[key] = found
        if isinstance(found, ContourError):
            raise found
        return found

    def along(self, planes, seed: int | np.random.Generator | None) -> Iterator[Planned]:
        """The contours of ``planes`` in order, lazily, each with a noise seed drawn from ``seed`` in turn (the
        noise draws of the "stream" scheme; :func:`touch` with ``planes``).

        Raises:
            ContourError: a plane misses the object.
        """
        noise_rng = np.random.default_rng(seed)
        for plane in planes:
            yield Planned(self.cut(plane), int(noise_rng.integers(2**31 - 1)))

    def draw(self, rng: np.random.Generator, *, cut_by: Toucher | None = None) -> Contour:
        """One contour through two candidate points drawn with ``rng``; planes that miss the object are re-drawn.
        ``cut_by``: the plane is drawn through this object's centre and points but cut by that Toucher (another
        model of the same object, e.g. a smoothed copy, that the contours are then pressed on: each plane cut once,
        where it is used); the contour returned is that cut.

        Raises:
            ContourError: ``MAX_DRAWS`` planes in a row missed the object (``cut_by``'s).
            InvalidArgumentError: ``cut_by`` is not a Toucher.
        """
        if cut_by is not None and not isinstance(cut_by, Toucher):
            raise InvalidArgumentError(f"{self.model.name}: cut_by must be a Toucher or None, got "
                                       f"{type(cut_by).__name__}")
        cutter = self if cut_by is None else cut_by
        for _ in range(sampling.MAX_DRAWS):
            plane = sampling.draw_plane(self.model, self.points, rng)
            try:
                return cutter.cut(plane)
            except ContourError as exc:
                log.debug("%s: re-drawing a plane (%s)", cutter.model.name, exc)
        raise ContourError(f"{cutter.model.name}: {sampling.MAX_DRAWS} planes in a row missed the object")

    def stream(self, n: int, seed: int | np.random.Generator | None, *, order_seed: int | None = None,
               start: int = 0) -> Iterator[Planned]:
        """``n`` contours of the "stream" scheme (module docstring), drawn lazily from one generator.

        Guided strategies take positions ``start, start + 1, ...`` of the pair order seeded with ``order_seed``
        (default: a number drawn from the generator first); a store passes the object's order seed and the row.
        """
        if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or start < 0:
            raise InvalidArgumentError(f"{self.model.name}: stream start must be an integer >= 0, got {start!r}")
        n = _check_contours(n, self.model.name)
        rng = np.random.default_rng(seed)
        if self.guided:
            order = self.pair_order(int(rng.integers(2**63)) if order_seed is None else order_seed)
            for k in range(start, start + n):
                yield Planned(self.cut(order[k]), int(rng.integers(2**31 - 1)))
            return
        for _ in range(n):
            contour = self.draw(rng)
            yield Planned(contour, int(rng.integers(2**31 - 1)))

    def by_object(self, n: int, seed: int) -> tuple[Iterator[Planned], np.random.Generator]:
        """``n`` contours of the "object" scheme (module docstring) and the generator of its pose jitter.

        The iterator raises ContourError when fewer than ``n`` of the ``n + SPARE_PLANES`` blind planes cut the
        object (a guided pair order holds only planes that cut: its first ``n`` positions are taken).
        """
        n = _check_contours(n, self.model.name)
        plane_seed, noise_seed, jitter_seed = object_seed(seed, self.model.name, self.strategy).spawn(3)
        plane_rng = np.random.default_rng(plane_seed)
        if self.guided:
            order = self.pair_order(int(plane_rng.integers(2**63)))
            planes = [order[k] for k in range(n)]
        else:
            planes = [sampling.draw_plane(self.model, self.points, plane_rng) for _ in range(n + SPARE_PLANES)]
        noise_seeds = np.random.default_rng(noise_seed).integers(2**31 - 1, size=len(planes))

        def planned() -> Iterator[Planned]:
            found = 0
            for plane, noise in zip(planes, noise_seeds):
                if found == n:
                    return
                try:
                    contour = self.cut(plane)
                except ContourError as exc:
                    log.debug("%s: skipping a plane (%s)", self.model.name, exc)
                    continue
                found += 1
                yield Planned(contour, int(noise))
            if found < n:
                raise ContourError(f"{self.model.name}: only {found} of {n} planes cut the object")

        return planned(), np.random.default_rng(jitter_seed)


def _stream_jitter_rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    """The pose-jitter generator of the "stream" scheme: independent of the plane and noise draws, which it
    leaves untouched (a Generator is spawned, which does not advance it)."""
    if isinstance(seed, np.random.Generator):
        return seed.spawn(1)[0]
    return np.random.default_rng(None if seed is None else [int(seed), zlib.crc32(b"jitter")])


def _press_planned(sensor: FSRSensor, model: ObjectModel, todo: list[tuple[Contour, Contour, int]],
                   strategy: str) -> list[TactileSequence]:
    """The sequences of ``todo``'s (planned, as pressed, noise seed) contours, pressed in one adaptive pass
    (:meth:`FSRSensor.press_contours`: the frames of one press per contour). Each records the planned poses: the
    robot does not know its jitter."""
    reads = sensor.press_contours(model, [pressed for _, pressed, _ in todo], [noise for _, _, noise in todo])
    return [TactileSequence.of_contour(model, contour, *read, seed=noise, strategy=strategy)
            for (contour, _, noise), read in zip(todo, reads)]


def touch(
    model: ObjectModel,
    strategy: str = "guided",
    n_contours: int = 10,
    sensor: FSRSensor | None = None,
    probes: int = 25,
    seed: int | np.random.Generator | None = 0,
    saliency: attention.Saliency | None = None,
    *,
    seeding: str = "stream",
    jitter_mm: float = 0.0,
    timing: TouchTiming | None = None,
    contours: list[Contour] | None = None,
    progress: bool = False,
    planes: list[Plane] | None = None,
) -> list[TactileSequence]:
    """Touch ``model`` along ``n_contours`` contours chosen by ``strategy``: one tactile sequence each.

    Args:
        sensor: the FSR pad (default ``FSRSensor()``); probes: probes per contour.
        seed: an integer (or, for ``seeding="stream"``, a Generator); same seed -> same sequences.
        saliency: a precomputed Saliency of the strategy's method (else computed: "stream" with seed 0,
            "object" with ``seed``).
        seeding: "stream" or "object" (see the module docstring).
        jitter_mm: pose jitter std, mm (0: press where planned). The sequences record the planned poses.
        timing: collects saliency and per-contour (cut + press) wall seconds.
        contours: if given, the planned contours are appended to it.
        progress: show a tqdm bar.
        planes: touch along these planes, in order, instead of drawing them (a touch policy's choices; the
            planes are given in ``model``'s frame); ``n_contours`` must be their number, the noise seeds are
            drawn from ``seed`` as in the "stream" scheme, and a plane that misses the object raises.

    Raises:
        InvalidArgumentError: ``model`` not an ObjectModel (an Open3D mesh or a path: load it with
            ``perception.load_object`` first), unknown strategy or seeding, n_contours not an integer >= 1 or
            above the contour limit, probes not an integer >= 2 or above the probe limit, a bad seed, a negative
            or non-finite jitter, or sequences that would not fit the memory limit (limits and their environment
            variables: :mod:`perception.limits`).
        ContourError: a flat object, too many planes that miss the object, or a given plane that misses it.
        SaliencyError: ``saliency`` is of another method or object.

    Examples:
        >>> from perception.shapes import make_object
        >>> from tactile import FSRSensor, touch
        >>> sequences = touch(make_object("box", 0), "blind", 2, FSRSensor(rows=8, cols=8), probes=5, seed=0)
        >>> len(sequences), sequences[0].frames.shape, sequences[0].strategy
        (2, (5, 8, 8), 'blind')
        >>> again = touch(make_object("box", 0), "blind", 2, FSRSensor(rows=8, cols=8), probes=5, seed=0)
        >>> all((a.frames == b.frames).all() for a, b in zip(sequences, again))  # same seed, same frames
        True
    """
    check_object_model(model, "touch")
    sampling.check_strategy(strategy)
    if seeding not in SEEDINGS:
        raise InvalidArgumentError(f"unknown seeding {seeding!r}; choose one of {', '.join(SEEDINGS)}")
    n_contours = _check_contours(n_contours, model.name)
    if planes is not None:
        planes = _check_planes(planes, model.name)
        if len(planes) != n_contours:
            raise InvalidArgumentError(f"{model.name}: {len(planes)} planes given for n_contours={n_contours}")
    seed = check_seed(seed, model.name)
    if seeding == "object" and not isinstance(seed, int):
        raise InvalidArgumentError(f"{model.name}: seeding 'object' needs an integer seed, got {seed!r}")
    jitter_mm = _check_jitter(jitter_mm, model.name)
    if sensor is not None and not isinstance(sensor, FSRSensor):
        raise InvalidArgumentError(f"{model.name}: sensor must be a tactile.FSRSensor, got {type(sensor).__name__}")
    sensor = sensor or FSRSensor()
    probes = _check_probes(probes, model.name)
    # The sequences are returned together: refuse, before any saliency or touch, what memory cannot hold.
    check_bytes(n_contours * sequence_nbytes(probes, sensor.rows, sensor.cols),
                f"{model.name}: touching {n_contours} contours ({probes} probes, {sensor.rows} x {sensor.cols} taxels)")
    toucher = Toucher(model, strategy, probes=probes, saliency=saliency,
                      saliency_seed=seed if seeding == "object" else 0, timing=timing)
    if planes is not None:
        planned = toucher.along(planes, seed)
        jitter_rng = None
    elif seeding == "object":
        planned, jitter_rng = toucher.by_object(n_contours, seed)
    else:
        planned = toucher.stream(n_contours, seed)
        jitter_rng = None
    # Timed touches are pressed one contour at a time (as a robot touches); the others are planned first and
    # pressed in one adaptive pass (FSRSensor.press_contours: the same frames, far fewer ray-casting calls).
    todo: list[tuple[Contour, Contour, int]] = []  # (planned, as pressed, noise seed)
    sequences = []
    steps = iter(progress_bar(range(n_contours), enabled=progress, desc=f"touch {model.name}"))
    while True:
        start = time.perf_counter()
        item = next(planned, None)
        if item is None:
            break
        next(steps, None)
        if jitter_mm > 0 and jitter_rng is None:  # the "stream" scheme's jitter: its own stream, made when needed
            jitter_rng = _stream_jitter_rng(seed)
        contour, pressed, noise = item.contour, jitter_contour(item.contour, jitter_mm, jitter_rng), item.noise_seed
        todo.append((contour, pressed, noise))
        if timing is not None:
            sequences += _press_planned(sensor, model, todo[-1:], strategy)
            timing.contour_seconds.append(time.perf_counter() - start)
    if timing is None:
        sequences = _press_planned(sensor, model, todo, strategy)
    if contours is not None:
        contours.extend(contour for contour, _, _ in todo)
    return sequences


def touch_variants(toucher: Toucher, planes: list[Plane], sensor: FSRSensor, variants) -> list[list[TactileSequence]]:
    """Touch ``toucher``'s object along ``planes`` once per variant: for each (seed, jitter_mm) of ``variants``,
    the sequences ``touch(toucher.model, toucher.strategy, len(planes), sensor, toucher.probes, seed,
    planes=planes, jitter_mm=jitter_mm)`` gives, bit for bit. The planes are cut once (by ``toucher``) and every
    variant is pressed in one adaptive pass (a touch policy simulating its candidates several ways).

    Raises:
        InvalidArgumentError: planes that are not an iterable of Plane, no planes or variants, a variant that is not
            (integer seed >= 0, jitter >= 0), a sensor that is not an FSRSensor, or sequences beyond the contour or
            memory limits.
        ContourError: a plane that misses the object.
    """
    if not isinstance(toucher, Toucher):
        raise InvalidArgumentError(f"touch_variants: toucher must be a Toucher, got {type(toucher).__name__}")
    model = toucher.model
    if not isinstance(sensor, FSRSensor):
        raise InvalidArgumentError(f"{model.name}: sensor must be a tactile.FSRSensor, got {type(sensor).__name__}")
    planes = _check_planes(planes, model.name)
    try:
        variants = list(variants)
    except TypeError:
        raise InvalidArgumentError(f"{model.name}: variants must be an iterable of (seed, jitter_mm), got "
                                   f"{type(variants).__name__}") from None
    if not planes or not variants:
        raise InvalidArgumentError(f"{model.name}: touch_variants needs at least one plane and one variant, got "
                                   f"{len(planes)} and {len(variants)}")
    checked = []
    for variant in variants:
        if not isinstance(variant, (tuple, list)) or len(variant) != 2:
            raise InvalidArgumentError(f"{model.name}: a variant must be (seed, jitter_mm), got {variant!r}")
        seed = check_seed(variant[0], model.name, allow_none=False)
        if not isinstance(seed, int):
            raise InvalidArgumentError(f"{model.name}: a variant's seed must be an integer, got {variant[0]!r}")
        checked.append((seed, _check_jitter(variant[1], model.name)))
    total = _check_contours(len(planes) * len(checked), model.name)
    check_bytes(total * sequence_nbytes(toucher.probes, sensor.rows, sensor.cols),
                f"{model.name}: touching {total} contours ({toucher.probes} probes, {sensor.rows} x {sensor.cols} "
                "taxels)")
    todo: list[tuple[Contour, Contour, int]] = []  # (planned, as pressed, noise seed), variant by variant
    for seed, jitter_mm in checked:
        jitter_rng = _stream_jitter_rng(seed) if jitter_mm > 0 else None
        for item in toucher.along(planes, seed):
            todo.append((item.contour, jitter_contour(item.contour, jitter_mm, jitter_rng), item.noise_seed))
    sequences = _press_planned(sensor, model, todo, toucher.strategy)
    return [sequences[i:i + len(planes)] for i in range(0, len(sequences), len(planes))]


#: :func:`touch` under the name the first scripts used (its defaults: the "stream" seed scheme of the stores).
explore_object = touch


__all__ = ["MAX_JITTER_MM", "SEEDINGS", "SPARE_PLANES", "TILT_DEG_PER_MM", "Planned", "TouchTiming", "Toucher",
           "check_strategy", "explore_object", "jitter_contour", "object_seed", "touch", "touch_variants"]
