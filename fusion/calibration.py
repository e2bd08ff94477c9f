"""Calibrated class probabilities: temperature scaling per touch, a tempered log rule for K touches, reliability.

A classifier's probabilities are calibrated when, among the decisions given confidence p, a share p is right. The
log rule (:func:`fusion.decide.fuse_touches`) adds the log probabilities of K touches as if they were independent
evidence; touches of one object are not, so its fused posteriors are overconfident. Two fitted numbers fix both:

- **temperature** T (per classifier): each touch's probabilities p become softmax(log p / T) (T > 1 softens);
- **dependence** rho in [0, 1] (the tempered log rule): K touches are fused as softmax(beta_K * sum_k log q_k) with
  beta_K = 1 / (1 + rho (K - 1)): rho = 0 is the log rule (independent touches), rho = 1 the geometric mean (K
  copies of one touch); K / (1 + rho (K - 1)) is the number of independent touches the K are worth.

Both are fitted by minimising the negative log-likelihood on probabilities of objects *held out inside the training
data* (:func:`fusion.openset.calibrate` does the folds); never on test objects. Reliability: :func:`reliability`
(bins of confidence vs accuracy), :func:`expected_calibration_error` (ECE), :func:`plot_reliability`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import log_softmax

from fusion.decide import PROBA_FLOOR
from perception.atomic import save_figure
from perception.errors import DatasetError, InvalidArgumentError, shown

#: Temperatures searched by :func:`fit_temperature` (dimensionless).
TEMPERATURE_BOUNDS = (0.02, 200.0)
#: Confidence bins of the ECE and the reliability diagrams (equal width over [0, 1]).
DEFAULT_BINS = 15


def _check_proba(proba, where: str, ndim=(2,)) -> np.ndarray:
    proba = np.asarray(proba, dtype=np.float64)
    if proba.ndim not in ndim or proba.shape[-1] < 2 or proba.size == 0:
        raise DatasetError(f"{where}: expected probabilities of shape {'/'.join(f'{d}-D' for d in ndim)} with >= 2 "
                           f"classes, got {proba.shape}")
    if not np.isfinite(proba).all() or (proba < 0).any():
        raise DatasetError(f"{where}: probabilities must be finite and non-negative")
    return proba


def _check_labels(y, n: int, n_classes: int, where: str) -> np.ndarray:
    y = np.asarray(y)
    if y.shape != (n,) or y.dtype.kind not in "iu" or (n and (y.min() < 0 or y.max() >= n_classes)):
        raise DatasetError(f"{where}: expected {n} class indices in 0..{n_classes - 1}, got shape {y.shape}, "
                           f"dtype {y.dtype}")
    return y.astype(np.int64)


def log_proba(proba) -> np.ndarray:
    """log of probabilities floored at :data:`fusion.decide.PROBA_FLOOR` (finite everywhere)."""
    return np.log(np.maximum(np.asarray(proba, dtype=np.float64), PROBA_FLOOR))


def check_temperature(temperature, where: str = "") -> float:
    """``temperature`` as a float; raise InvalidArgumentError (its message starting with ``where``) unless a real
    number, finite and > 0 (an integer too large for a float counts as infinite)."""
    t = math.nan
    if not isinstance(temperature, bool) and isinstance(temperature, (int, float, np.integer, np.floating)):
        try:
            t = float(temperature)
        except OverflowError:
            t = math.inf
    if not 0 < t < math.inf:  # NaN fails it too
        raise InvalidArgumentError(f"{where}temperature must be a finite number > 0, got {shown(temperature)}")
    return t


def check_dependence(dependence) -> float:
    """``dependence`` (rho) as a float; raise InvalidArgumentError unless in [0, 1]."""
    if isinstance(dependence, bool) or not isinstance(dependence, (int, float, np.integer, np.floating)) or not (
            0.0 <= dependence <= 1.0):
        raise InvalidArgumentError(f"dependence (rho) must be a number in [0, 1], got {dependence!r}")
    return float(dependence)


def apply_temperature(proba, temperature: float) -> np.ndarray:
    """(..., C) probabilities softened (T > 1) or sharpened (T < 1): softmax(log p / T) along the last axis.

    Raises:
        DatasetError: bad probabilities. InvalidArgumentError: T not finite and > 0.
    """
    proba = _check_proba(proba, "apply_temperature", ndim=(1, 2, 3))
    t = check_temperature(temperature)
    return np.exp(log_softmax(log_proba(proba) / t, axis=-1))


def tempered_exponent(k, dependence: float) -> np.ndarray | float:
    """beta_K = 1 / (1 + rho (K - 1)): the weight of each touch's log probabilities when K touches are fused."""
    rho = check_dependence(dependence)
    k = np.asarray(k, dtype=np.float64)
    if (k < 1).any():
        raise InvalidArgumentError(f"touch counts must be >= 1, got {k.min()}")
    beta = 1.0 / (1.0 + rho * (k - 1.0))
    return float(beta) if beta.ndim == 0 else beta


def fuse_tempered(proba, dependence: float) -> np.ndarray:
    """Fuse (K, C) -> (C,) or (N, K, C) -> (N, C) probabilities by the tempered log rule (module docstring).

    Raises:
        DatasetError: bad probabilities. InvalidArgumentError: rho outside [0, 1].
    """
    proba = _check_proba(proba, "fuse_tempered", ndim=(2, 3))
    beta = tempered_exponent(proba.shape[-2], dependence)
    return np.exp(log_softmax(beta * log_proba(proba).sum(axis=-2), axis=-1))


def negative_log_likelihood(proba, y) -> float:
    """Mean -log p(true class) (nats), probabilities floored at PROBA_FLOOR."""
    proba = _check_proba(proba, "negative_log_likelihood")
    y = _check_labels(y, len(proba), proba.shape[1], "negative_log_likelihood")
    return float(-log_proba(proba[np.arange(len(y)), y]).mean())


def _checked_logits(logits, y, bounds, where: str) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(logits, labels, low T, high T) checked for the temperature fits: finite (N >= 2, C >= 2) logits, N class
    indices, and 0 < low < high < inf (DatasetError / InvalidArgumentError naming ``where``)."""
    z = np.asarray(logits, dtype=np.float64)
    if z.ndim != 2 or z.shape[1] < 2 or len(z) < 2 or not np.isfinite(z).all():
        raise DatasetError(f"{where}: expected finite (N >= 2, C >= 2) logits, got shape {z.shape}")
    y = _check_labels(y, len(z), z.shape[1], where)
    lo, hi = (float(b) for b in bounds)
    if not 0 < lo < hi or not np.isfinite(hi):
        raise InvalidArgumentError(f"{where}: bounds must satisfy 0 < low < high < inf, got {bounds!r}")
    return z, y, lo, hi


def fit_temperature(logits, y, *, bounds=TEMPERATURE_BOUNDS) -> float:
    """The temperature T minimising the mean NLL of softmax(logits / T) for true classes ``y``.

    Args:
        logits: (N, C) scores (any additive shift per row); for a classifier that gives probabilities, their log
            (:func:`log_proba`).
        y: (N,) true class indices.
        bounds: the searched interval of T (a fit at a bound is returned as that bound).

    Raises:
        DatasetError: bad shapes, non-finite logits, or fewer than 2 samples. InvalidArgumentError: bounds not
            0 < low < high < inf.
    """
    z, y, lo, hi = _checked_logits(logits, y, bounds, "fit_temperature")
    rows = np.arange(len(y))

    def nll(log_t: float) -> float:
        return float(-log_softmax(z / np.exp(log_t), axis=1)[rows, y].mean())

    result = minimize_scalar(nll, bounds=(np.log(lo), np.log(hi)), method="bounded", options={"xatol": 1e-5})
    return float(np.clip(np.exp(result.x), lo, hi))


def apply_calibration(proba, temperature: float, smoothing: float = 0.0) -> np.ndarray:
    """(..., C) probabilities temperature-scaled, then mixed with the uniform distribution:
    (1 - eps) softmax(log p / T) + eps / C, eps = ``smoothing`` in [0, 1).

    Raises:
        DatasetError: bad probabilities. InvalidArgumentError: T not finite and > 0, or eps outside [0, 1).
    """
    eps = check_smoothing(smoothing)
    q = apply_temperature(proba, temperature)
    return (1.0 - eps) * q + eps / q.shape[-1]


def check_smoothing(smoothing) -> float:
    """``smoothing`` (eps) as a float; raise InvalidArgumentError unless in [0, 1)."""
    if isinstance(smoothing, bool) or not isinstance(smoothing, (int, float, np.integer, np.floating)) or not (
            0.0 <= smoothing < 1.0):
        raise InvalidArgumentError(f"smoothing (eps) must be a number in [0, 1), got {smoothing!r}")
    return float(smoothing)


def fit_calibration(logits, y, *, bounds=TEMPERATURE_BOUNDS, max_smoothing: float = 0.5) -> tuple[float, float]:
    """(T, eps) minimising the mean NLL of (1 - eps) softmax(logits / T) + eps / C (:func:`apply_calibration`).

    Temperature alone is the usual choice, but a classifier whose touches sometimes rule the true class out
    (probability near 0: a touch on a part that looks like another class) makes the NLL-optimal T soften every
    decision to pay for those few; the uniform share eps pays for them instead, so T can fit the rest.

    Raises:
        DatasetError: bad shapes, non-finite logits, or fewer than 2 samples. InvalidArgumentError: bounds not
            0 < low < high < inf.
    """
    from scipy.optimize import minimize

    z, y, lo, hi = _checked_logits(logits, y, bounds, "fit_calibration")
    rows, c = np.arange(len(y)), z.shape[1]

    def nll(params) -> float:
        t, eps = np.exp(params[0]), max_smoothing / (1.0 + np.exp(-params[1]))
        q = np.exp(log_softmax(z / t, axis=1)[rows, y])
        return float(-np.log((1.0 - eps) * q + eps / c).mean())

    t0 = fit_temperature(z, y, bounds=bounds)
    best = None
    for start in ((np.log(t0), -6.0), (0.0, -3.0), (np.log(t0), 0.0)):
        res = minimize(nll, np.array(start), method="L-BFGS-B",
                       bounds=[(np.log(lo), np.log(hi)), (-20.0, 20.0)])
        if best is None or res.fun < best.fun:
            best = res
    t, eps = float(np.exp(best.x[0])), float(max_smoothing / (1.0 + np.exp(-best.x[1])))
    return float(np.clip(t, lo, hi)), eps


def fit_confidence_map(proba, y) -> tuple[np.ndarray, np.ndarray]:
    """An increasing map of confidence (max probability) to the share right, fitted by isotonic regression on
    (N, C) probabilities and true classes ``y``: (knots (M,), values (M,)), both in [0, 1], for :func:`apply_confidence_map`.

    The temperature family cannot bend a reliability curve that is too flat at one end and too steep at the other
    (the conventional SVM's, whose Platt probabilities rarely pass 0.85); this map can, and keeps every decision's
    class (top-label calibration).

    Raises:
        DatasetError: bad shapes or labels.
    """
    from sklearn.isotonic import IsotonicRegression

    proba = _check_proba(proba, "fit_confidence_map")
    y = _check_labels(y, len(proba), proba.shape[1], "fit_confidence_map")
    confidence = proba.max(axis=1)
    right = (proba.argmax(axis=1) == y).astype(np.float64)
    iso = IsotonicRegression(y_min=1.0 / proba.shape[1], y_max=1.0, increasing=True, out_of_bounds="clip")
    iso.fit(confidence, right)
    knots = np.asarray(iso.X_thresholds_, dtype=np.float64)
    values = np.asarray(iso.y_thresholds_, dtype=np.float64)
    return knots, values


def apply_confidence_map(proba, knots, values) -> np.ndarray:
    """(..., C) probabilities whose max becomes ``values`` interpolated at it (:func:`fit_confidence_map`), the
    other classes rescaled to share the rest in their old proportions; the most probable class never changes.

    Raises:
        DatasetError: bad probabilities or map.
    """
    proba = _check_proba(proba, "apply_confidence_map", ndim=(1, 2, 3))
    knots, values = np.asarray(knots, dtype=np.float64), np.asarray(values, dtype=np.float64)
    if knots.ndim != 1 or knots.shape != values.shape or len(knots) == 0 or not (
            np.isfinite(knots).all() and np.isfinite(values).all()) or (np.diff(knots) < 0).any():
        raise DatasetError("apply_confidence_map: knots and values must be equal, finite, sorted 1-D arrays")
    proba = proba / proba.sum(axis=-1, keepdims=True)
    top = proba.max(axis=-1, keepdims=True)
    rest = 1.0 - top
    srt = np.sort(proba, axis=-1)
    second = srt[..., -2:-1]
    new_top = np.interp(top, knots, values)
    # keep the decision: the top must stay above the rescaled runner-up
    # (a certain decision's rest is shared evenly, so its top must stay above 1 / C)
    keep = np.where(rest > 1e-15, second / np.maximum(rest + second, 1e-300), 1.0 / proba.shape[-1]) * (1.0 + 1e-6)
    new_top = np.clip(np.maximum(new_top, keep), 1.0 / proba.shape[-1], 1.0)
    is_top = proba == top
    first = is_top & (np.cumsum(is_top, axis=-1) == 1)
    scale = np.where(rest > 1e-15, (1.0 - new_top) / np.maximum(rest, 1e-15), 0.0)
    others = np.where(rest > 1e-15, proba * scale, (1.0 - new_top) / max(proba.shape[-1] - 1, 1))
    out = np.where(first, new_top, others)
    return out / out.sum(axis=-1, keepdims=True)


def fit_dependence(groups_proba, groups_y) -> float:
    """rho in [0, 1] minimising the mean NLL of the tempered log rule over touch groups of several sizes.

    Args:
        groups_proba: list of (N_k, K, C) calibrated per-touch probabilities (one entry per K; K = 1 adds nothing).
        groups_y: list of (N_k,) true class indices.

    Raises:
        DatasetError: mismatched lists or shapes, or no group with K >= 2.
    """
    if len(groups_proba) != len(groups_y):
        raise DatasetError(f"fit_dependence: {len(groups_proba)} probability sets for {len(groups_y)} label sets")
    sets = []
    for proba, y in zip(groups_proba, groups_y):
        proba = _check_proba(proba, "fit_dependence", ndim=(3,))
        y = _check_labels(y, len(proba), proba.shape[2], "fit_dependence")
        if proba.shape[1] >= 2:
            sets.append((log_proba(proba).sum(axis=1), proba.shape[1], y))
    if not sets:
        raise DatasetError("fit_dependence: no touch groups of K >= 2 to fit the dependence on")

    def nll(rho: float) -> float:
        total = 0.0
        for summed, k, y in sets:  # each K weighs the same, however many groups it has
            total += -log_softmax(summed / (1.0 + rho * (k - 1)), axis=1)[np.arange(len(y)), y].mean()
        return float(total / len(sets))

    result = minimize_scalar(nll, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-5})
    candidates = [0.0, float(result.x), 1.0]  # the bounded search never evaluates the ends themselves
    return float(min(candidates, key=nll))


def reliability(proba, y, bins: int = DEFAULT_BINS) -> dict:
    """Reliability bins of (N, C) probabilities: equal-width bins of confidence (max probability) in [0, 1].

    Returns:
        {"edges": (B + 1,), "count": (B,) decisions per bin, "confidence": (B,) their mean confidence, "accuracy":
        (B,) their share right (0 where a bin is empty), "ece": expected calibration error (the count-weighted mean
        |accuracy - confidence|), "n": N}.

    Raises:
        DatasetError: bad shapes or labels. InvalidArgumentError: bins < 1.
    """
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise InvalidArgumentError(f"reliability: bins must be an integer >= 1, got {bins!r}")
    proba = _check_proba(proba, "reliability")
    y = _check_labels(y, len(proba), proba.shape[1], "reliability")
    return _binned(proba.max(axis=1), (proba.argmax(axis=1) == y).astype(np.float64), bins)


def _binned(confidence: np.ndarray, right: np.ndarray, bins: int) -> dict:
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.searchsorted(edges, confidence, side="left") - 1, 0, bins - 1)  # (lo, hi] bins, 0 in the first
    count = np.bincount(which, minlength=bins).astype(np.int64)
    safe = np.maximum(count, 1)
    mean_conf = np.bincount(which, weights=confidence, minlength=bins) / safe
    mean_acc = np.bincount(which, weights=right, minlength=bins) / safe
    ece = float(np.sum(count * np.abs(mean_acc - mean_conf)) / len(right))
    return {"edges": edges, "count": count, "confidence": mean_conf, "accuracy": mean_acc, "ece": ece,
            "n": len(right)}


def expected_calibration_error(proba, y, bins: int = DEFAULT_BINS) -> float:
    """ECE of (N, C) probabilities against true class indices ``y`` (see :func:`reliability`), in [0, 1]."""
    return reliability(proba, y, bins)["ece"]


def ece_interval(proba, y, groups, *, bins: int = DEFAULT_BINS, n_boot: int = 1000, seed: int = 0) -> dict:
    """ECE with a 95 % percentile-bootstrap interval over ``groups`` (e.g. objects: whole groups resampled).

    Returns:
        {"ece", "low", "high", "n", "n_groups"}.
    """
    proba = _check_proba(proba, "ece_interval")
    y = _check_labels(y, len(proba), proba.shape[1], "ece_interval")
    groups = np.asarray(groups)
    if groups.shape != (len(y),):
        raise DatasetError(f"ece_interval: {groups.shape} groups for {len(y)} decisions")
    value = expected_calibration_error(proba, y, bins)
    names, inverse = np.unique(groups, return_inverse=True)
    members = [np.flatnonzero(inverse == g) for g in range(len(names))]
    rng = np.random.default_rng(seed)
    boot = np.empty(n_boot)
    for b in range(n_boot):
        pick = np.concatenate([members[g] for g in rng.integers(0, len(names), len(names))])
        boot[b] = expected_calibration_error(proba[pick], y[pick], bins)
    low, high = np.percentile(boot, [2.5, 97.5])
    return {"ece": value, "low": float(low), "high": float(high), "n": len(y), "n_groups": len(names)}


def ece_noise_floor(confidence, bins: int = DEFAULT_BINS, draws: int = 200, seed: int = 0) -> float:
    """The mean ECE of a *perfectly calibrated* predictor with these (N,) confidences: each decision right with
    probability its confidence, ``draws`` seeded draws. A finite sample's ECE is biased upwards; a measured ECE near
    this floor is as good as N decisions can show."""
    confidence = np.asarray(confidence, dtype=np.float64).ravel()
    if len(confidence) == 0 or not np.isfinite(confidence).all() or (confidence < 0).any() or (confidence > 1).any():
        raise DatasetError("ece_noise_floor: confidences must be finite values in [0, 1]")
    rng = np.random.default_rng(seed)
    return float(np.mean([_binned(confidence, (rng.random(len(confidence)) < confidence).astype(np.float64), bins)["ece"]
                          for _ in range(draws)]))


def plot_reliability(curves: dict, path, title: str = "") -> object:
    """A reliability diagram (PNG) of several named ``curves``: name -> :func:`reliability` result."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.2, 4.6), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="calibrated")
    for i, (name, rel) in enumerate(curves.items()):
        used = np.asarray(rel["count"]) > 0
        ax.plot(np.asarray(rel["confidence"])[used], np.asarray(rel["accuracy"])[used], marker="o", markersize=3,
                color=f"C{i % 10}", label=f"{name} (ECE {rel['ece']:.3f})")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("confidence (max probability)")
    ax.set_ylabel("share right")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    return save_figure(fig, path, dpi=120)


__all__ = [
    "DEFAULT_BINS",
    "TEMPERATURE_BOUNDS",
    "apply_calibration",
    "apply_confidence_map",
    "apply_temperature",
    "check_dependence",
    "check_smoothing",
    "check_temperature",
    "ece_interval",
    "ece_noise_floor",
    "expected_calibration_error",
    "fit_calibration",
    "fit_confidence_map",
    "fit_dependence",
    "fit_temperature",
    "fuse_tempered",
    "log_proba",
    "negative_log_likelihood",
    "plot_reliability",
    "reliability",
    "tempered_exponent",
]
