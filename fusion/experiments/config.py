"""Sizes of the experiments: the full run, ``--quick`` and the demo, in one place (and in every report).

Contour counts are per object and per strategy. The paper protocol uses the paper's 950 contours per object;
the parts beyond the paper use fewer, chosen so the full run of the default parts fits in 30 minutes and ``--quick``
with every part in 5 on two CPU cores (the full run with every part, the opt-in calibration, open-set and active
parts too, took 52 minutes on 2026-12-04: README); see the report's "Sizes" section for what a run used.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from perception.errors import InvalidArgumentError
from tactile.sampling import PAPER_STRATEGIES
from tactile.touching import TILT_DEG_PER_MM

#: Noise kinds of the robustness part and what their level means.
NOISE_KINDS = {
    "taxel_noise": "Gaussian taxel noise, std in mm of gap",
    "dead_taxels": "fraction of dead taxels (read the sensing range)",
    "dead_taxels_repaired": "the same dead taxels, found in each sequence and filled in from their live "
                            "neighbours before classifying (tactile.dead_taxels)",
    "pose_jitter": f"probe position jitter std in mm (tilt std: {TILT_DEG_PER_MM} degrees per mm)",
}


@dataclass(frozen=True)
class Sizes:
    """How big each part of :func:`fusion.experiments.reproduce` is.

    Attributes:
        strategies: the sampling strategies compared in every part but ``attention`` (the paper: guided and
            blind).
        paper_classes: classes of the paper protocol when none are named (the first ones, sorted; the paper
            used 8).
        objects_per_class: instances per class of the paper protocol (the first ones, sorted by file name).
        paper_contours: contours per object and strategy of the paper protocol (the paper: 950).
        test_fraction: the paper protocol's held-out share of sequences (the paper: 0.2).
        unseen_contours, unseen_folds: contours per object of the unseen-objects part and its grouped
            k-fold by object.
        unseen_per_class: instances per class of the unseen-objects part (None: all).
        unseen_train_contours: contours per training object of the unseen-objects folds (None: ``unseen_contours``);
            the test objects keep ``unseen_contours`` each, so more training contours change what the models learn
            from, not what they are scored on. Left at None by nested cross-validation (inner grouped 3-fold inside
            each of the three training folds, CNN pair, guided + blind): 72 against 24 contours raised inner single
            touches by +1.5 / +2.3 / +0.2 points (guided and blind averaged, per outer fold), under the one point
            set beforehand for three times the data in the third fold (inner CNN fits 123-183 s against 40-46 s).
        touches: K, the contours per decision.
        noise_contours: contours per test object (of the unseen-objects folds) for each noise level (same seed at
            every level).
        noise_levels: kind -> levels (see :data:`NOISE_KINDS`); level 0 (clean) is always added.
        attention_contours, attention_folds: per object, and the grouped k-fold by object, of the attention
            comparison (paper objects).
        runtime_contours: contours per object of each (probes, grid) store of the error-vs-run-time part.
        runtime_strategies: the strategies timed there (default guided, the paper's method; its saliency
            time is stated separately).
        runtime_probes, runtime_grids: probes per contour and taxel grids (n x n) compared there.
        epochs: CNN epochs (None: the classifier's default).
        paper_classifiers, unseen_classifiers: which classifiers (see ``fusion.experiments.models``) each
            part trains (the run-time and noise parts use the unseen ones, attention the first of them).
        calibration_classifiers, calibration_strategy: the classifiers and the strategy of the calibration and
            open-set parts (unseen-objects store, any pose; :mod:`fusion.experiments.openset`).
        openset_rotations: rotations of the open-set part (the classes are dealt to them; each leaves its own out).
        active_*: the active-touch part (:meth:`active_options`, :mod:`fusion.experiments.active`).
    """

    strategies: tuple[str, ...] = PAPER_STRATEGIES
    paper_classes: int = 8
    objects_per_class: int = 3
    paper_contours: int = 950
    test_fraction: float = 0.2
    unseen_contours: int = 24
    unseen_folds: int = 3
    unseen_per_class: int | None = None
    unseen_train_contours: int | None = None
    touches: tuple[int, ...] = (1, 2, 4, 8)
    noise_contours: int = 4
    noise_levels: dict = field(
        default_factory=lambda: {
            "taxel_noise": (0.1, 0.3, 1.0),
            "dead_taxels": (0.05, 0.2, 0.5),
            "dead_taxels_repaired": (0.05, 0.2, 0.5),
            "pose_jitter": (0.5, 1.0, 2.0),
        }
    )
    attention_contours: int = 40
    attention_folds: int = 3
    runtime_contours: int = 20
    runtime_strategies: tuple[str, ...] = ("guided",)
    runtime_probes: tuple[int, ...] = (5, 10, 25, 50)
    runtime_grids: tuple[int, ...] = (8, 16, 32)
    epochs: int | None = None
    paper_classifiers: tuple[str, ...] = ("cnn-normals", "svm-normals", "knn-normals")
    unseen_classifiers: tuple[str, ...] = ("cnn", "svm", "knn")
    calibration_classifiers: tuple[str, ...] = ("cnn", "knn")
    calibration_strategy: str = "blind"
    openset_rotations: int = 5
    active_policies: tuple[str, ...] = ("random", "saliency", "information")
    active_touches: int = 8
    active_candidates: int = 24
    active_variants: int = 2
    active_noise_mm: float = 1.0
    active_visual: str = "noisy"
    active_episodes: int = 5

    def __post_init__(self) -> None:
        for name in ("paper_classes", "objects_per_class", "paper_contours", "unseen_contours", "noise_contours",
                     "attention_contours", "runtime_contours", "active_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InvalidArgumentError(f"Sizes.{name} must be a positive integer, got {value!r}")
        train = self.unseen_train_contours
        if train is not None and (isinstance(train, bool) or not isinstance(train, int) or train < 1):
            raise InvalidArgumentError(f"Sizes.unseen_train_contours must be a positive integer or None, got {train!r}")
        epochs = self.epochs  # None: the classifier's default (0 must not mean that: it is refused, as -1 is)
        if epochs is not None and (isinstance(epochs, bool) or not isinstance(epochs, int) or epochs < 1):
            raise InvalidArgumentError(f"Sizes.epochs (--epochs) must be a positive integer or None (the "
                                       f"classifier's default), got {epochs!r}")
        for name in ("unseen_folds", "attention_folds", "openset_rotations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 2:
                raise InvalidArgumentError(f"Sizes.{name} must be an integer of at least 2, got {value!r}")
        if not 0 < self.test_fraction < 1:
            raise InvalidArgumentError(f"Sizes.test_fraction must be in (0, 1), got {self.test_fraction!r}")
        if not self.touches or min(self.touches) < 1:
            raise InvalidArgumentError(f"Sizes.touches must be positive integers, got {self.touches!r}")
        from tactile.sampling import STRATEGIES

        for name in ("strategies", "runtime_strategies"):
            value = getattr(self, name)
            if not value or set(value) - set(STRATEGIES):
                raise InvalidArgumentError(f"Sizes.{name} must be among {list(STRATEGIES)}, got {value!r}")
        unknown = set(self.noise_levels) - set(NOISE_KINDS)
        if unknown:
            raise InvalidArgumentError(f"Sizes.noise_levels: unknown kinds {sorted(unknown)}; use {list(NOISE_KINDS)}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["noise_levels"] = {k: list(v) for k, v in self.noise_levels.items()}
        return d

    def with_(self, **changes) -> Sizes:
        return replace(self, **changes)

    def active_options(self) -> dict:
        """The keyword arguments of :func:`fusion.experiments.active.active_part` (the ``active_*`` sizes: its
        policies, touch budget, information-policy candidates x variants, the visual model's noise, what the
        policies plan on, "noisy" or "camera", and the episodes per object and policy)."""
        return {"policies": tuple(self.active_policies), "max_touches": self.active_touches,
                "candidates": self.active_candidates, "variants": self.active_variants,
                "noise_mm": self.active_noise_mm, "visual": self.active_visual, "episodes": self.active_episodes}


#: The full run (target: the default parts within 30 minutes on 2 cores).
FULL = Sizes()

#: ``--quick`` (target: within 5 minutes on 2 cores, smoke-sized: a check that every part runs, not a measurement).
QUICK = Sizes(
    paper_contours=60,
    unseen_contours=16,
    unseen_folds=3,
    unseen_per_class=4,
    noise_contours=3,
    noise_levels={"taxel_noise": (0.3, 1.0), "dead_taxels": (0.2, 0.5), "dead_taxels_repaired": (0.2, 0.5),
                  "pose_jitter": (1.0, 2.0)},
    attention_contours=16,
    runtime_contours=16,
    runtime_probes=(5, 25),
    runtime_grids=(8, 32),
    epochs=10,  # 5 stopped the CNN pair short of convergence (69 % on SHREC quick)
    openset_rotations=2,  # each leaves 5 of SHREC's 10 classes out: 2 x 8 calibration fits instead of 5 x 8
    active_policies=("random", "information"),
    active_candidates=12,
    active_variants=1,
    active_episodes=1,
)
