"""Recognizing one object: touch a mesh along K contours, classify each sequence, fuse the K decisions.

What ``visuotactile recognize`` runs: the model's own sensor and probe count are used, contours are chosen by
a sampling strategy (guided: the multiview saliency's interest points), and the per-touch probabilities are
fused with the sum of log probabilities (:func:`fusion.decide.fuse_touches`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.base import TactileClassifier
from fusion.openset import UNKNOWN, answer
from perception.atomic import save_figure
from perception.errors import InvalidArgumentError
from perception.geometry import ObjectModel
from tactile.contours import Contour
from tactile.explore import SequenceBatch
from tactile.touching import TouchTiming, touch

log = logging.getLogger(__name__)


@dataclass
class Recognition:
    """The outcome of :func:`recognize`.

    Attributes:
        label: the recognized class.
        probabilities: class -> fused probability (sums to 1).
        per_touch: (K, C) probabilities of each touch, columns in ``classes`` order.
        classes: the model's classes.
        contours: the K contours touched.
        rule: the fusion rule.
        seconds: {"saliency", "touching", "inference"} wall seconds.
        closest: the most probable known class (``label`` unless the answer is ``"unknown"``).
        known_score, threshold: a calibrated model's score of how well the touches fit a known class and its
            reject threshold for K touches (:mod:`fusion.openset`); None for a model without a reject option.
    """

    label: str
    probabilities: dict[str, float]
    per_touch: np.ndarray
    classes: list[str]
    contours: list[Contour]
    rule: str
    seconds: dict[str, float]
    closest: str | None = None
    known_score: float | None = None
    threshold: float | None = None

    @property
    def unknown(self) -> bool:
        """Whether the model answered "unknown" (the touches fit no known class well enough)."""
        return self.known_score is not None and self.threshold is not None and self.known_score < self.threshold

    def summary(self) -> str:
        """One line: 'mug (87.0 %)', or 'unknown; closest: mug, 0.41'."""
        closest = self.closest or self.label
        if self.unknown:
            return f"unknown; closest: {closest}, {self.probabilities[closest]:.2f}"
        return f"{self.label} ({100 * self.probabilities[self.label]:.1f} %)"

    def to_dict(self) -> dict:
        open_set = {} if self.known_score is None else {
            "unknown": self.unknown, "closest": self.closest, "known_score": round(self.known_score, 6),
            "threshold": round(float(self.threshold), 6)}
        return {
            **open_set,
            "label": self.label,
            "probabilities": {k: round(v, 6) for k, v in self.probabilities.items()},
            "per_touch": [
                {"label": self.classes[int(np.argmax(p))], "probability": round(float(p.max()), 6),
                 "plane_normal": [round(float(x), 6) for x in c.plane.normal]}
                for p, c in zip(self.per_touch, self.contours)
            ],
            "rule": self.rule,
            "seconds": {k: round(v, 4) for k, v in self.seconds.items()},
        }


def recognize(model: TactileClassifier, obj: ObjectModel, *, touches: int = 4, strategy: str = "guided",
              seed: int = 0, rule: str | None = None) -> Recognition:
    """Touch ``obj`` along ``touches`` contours chosen by ``strategy`` with the model's sensor, classify.

    ``rule``: the fusion rule (default: the tempered log rule for a calibrated model, else the log rule). A model
    calibrated with a reject option (:func:`fusion.openset.calibrate`) answers ``"unknown"`` when the touches fit
    no known class (``label`` is then "unknown" and ``closest`` the best known class).

    Raises:
        InvalidArgumentError: touches < 1. ContourError: unknown strategy, or planes that miss the object.

    Examples:
        >>> from fusion.conventional import ConventionalClassifier
        >>> from fusion.experiments.touch import touch_objects
        >>> from perception.shapes import make_object
        >>> seen = [make_object("box", 0), make_object("can", 0)]
        >>> model = ConventionalClassifier(kind="svm").fit(touch_objects(seen, ["box", "can"], "blind", 4, probes=10))
        >>> result = recognize(model, make_object("can", 1), touches=2, strategy="blind")
        >>> result.label in ("box", "can"), result.per_touch.shape, round(sum(result.probabilities.values()), 6)
        (True, (2, 2), 1.0)
    """
    if isinstance(touches, bool) or int(touches) != touches or touches < 1:
        raise InvalidArgumentError(f"touches must be a positive integer, got {touches!r}")
    timing = TouchTiming()
    contours: list[Contour] = []
    sequences = touch(obj, strategy, int(touches), model.sensor(), model.probes, seed, seeding="object",
                      timing=timing, contours=contours)
    # the object's own label (if any) plays no part; it may name a class the model never learned
    sequences = [dataclasses.replace(s, label=None) for s in sequences]
    batch = SequenceBatch.from_sequences(sequences, class_names=[str(c) for c in model.classes_],
                                         sensor_spec=model.sensor().spec())
    start = time.perf_counter()
    per_touch = model.predict_proba(batch)
    decision = answer(model, batch, rule=rule, proba=per_touch)
    fused = decision["fused"]
    inference = time.perf_counter() - start
    classes = [str(c) for c in model.classes_]
    closest = classes[int(np.argmax(fused))]
    result = Recognition(
        label=closest,
        probabilities=dict(sorted(zip(classes, map(float, fused)), key=lambda kv: -kv[1])),
        per_touch=per_touch, classes=classes, contours=contours, rule=decision["rule"],
        seconds={"saliency": sum(timing.saliency_seconds), "touching": sum(timing.contour_seconds),
                 "inference": inference},
        closest=closest, known_score=decision["known_score"], threshold=decision["threshold"],
    )
    if result.unknown:
        result.label = UNKNOWN
    return result


def recognize_file(mesh: str | Path, model_path: str | Path, *, touches: int = 4, strategy: str = "guided",
                   seed: int = 0, rule: str | None = None, trust_pickle: bool = False) -> tuple[ObjectModel, Recognition]:
    """:func:`recognize` a mesh file with a model file: the strategy is checked first, then the model and the mesh
    are loaded (pose-free frame, no label). Returns the object as touched and the recognition.

    Raises:
        InvalidArgumentError: an unknown strategy (before anything loads), touches < 1.
        DatasetError: no model file at ``model_path``. ModelFileError, MeshLoadError, ...: what loading raises.
    """
    from fusion.base import load_model
    from perception.errors import DatasetError
    from perception.loading import load_object
    from tactile.touching import check_strategy

    check_strategy(strategy)
    if not Path(model_path).is_file():
        raise DatasetError(f"{model_path}: no model there; run `visuotactile demo` (writes out/demo/models/cnn.vtm) "
                           "or `visuotactile train`, or pass --model")
    model = load_model(model_path, trust_pickle=trust_pickle)
    obj = load_object(mesh, label=None)
    return obj, recognize(model, obj, touches=touches, strategy=strategy, seed=seed, rule=rule)


def plot_recognition(obj: ObjectModel, result: Recognition, path: str | Path, top: int = 8) -> Path:
    """The touched contours and probes on the object (3D) next to the fused class probabilities (PNG)."""
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the 3d projection)

    fig = Figure(figsize=(11, 5), layout="constrained")
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    v = obj.vertices
    step = max(1, len(v) // 4000)
    ax.scatter(*v[::step].T, s=1.5, c="0.55", alpha=0.35, linewidths=0)
    colours = [f"C{i % 10}" for i in range(len(result.contours))]
    for i, (contour, colour) in enumerate(zip(result.contours, colours)):
        loop = np.vstack([contour.polyline, contour.polyline[:1]]) if contour.closed else contour.polyline
        guess = result.classes[int(np.argmax(result.per_touch[i]))]
        ax.plot(*loop.T, color=colour, linewidth=1.4, label=f"touch {i + 1}: {guess}")
        ax.scatter(*contour.positions.T, color=colour, s=8, depthshade=False)
    lo, hi = obj.bounds
    half, centre = 0.5 * (hi - lo).max(), 0.5 * (lo + hi)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        setter(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_title(f"{obj.name}: {len(result.contours)} contours touched", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    bars = fig.add_subplot(1, 2, 2)
    items = list(result.probabilities.items())[:top][::-1]
    bars.barh([k for k, _ in items], [100 * p for _, p in items],
              color=["tab:green" if k == result.label else "tab:orange" if k == result.closest and result.unknown
                     else "tab:gray" for k, _ in items])
    bars.set_xlim(0, 100)
    bars.set_xlabel(f"probability % (K = {len(result.contours)} touches, rule: "
                    f"{ {'log': 'sum of log', 'tempered': 'tempered log'}.get(result.rule, result.rule)})")
    bars.set_title(f"recognized: {result.summary()}", fontsize=10)
    return save_figure(fig, path, dpi=120)


__all__ = ["Recognition", "plot_recognition", "recognize", "recognize_file"]
