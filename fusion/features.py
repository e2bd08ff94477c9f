"""The paper's hand-made features as scikit-learn transformers (Rouhafzay & Cretu 2019, DESIGN.md section 4).

Steps, in :func:`fusion.conventional.conventional_pipeline` order:

1. :class:`SequenceSeries` -- a :class:`~tactile.explore.SequenceBatch` to ``F`` series of ``P`` probes per
   sequence: per frame the std of each of the 16 finest contourlet subbands (:func:`fusion.contourlet.subband_std`)
   and the kinesthetic cue (3 normal components, or 6 pose-invariant cues: :mod:`fusion.cues`), so F = 19 or 22.
   Output (S, F * P), series-major (column ``f * P + p``). This step takes a batch, not a 2-D array, so it
   cannot run scikit-learn's estimator checks (they feed random 2-D arrays); the contourlet part is cached
   per batch (:func:`sequence_features`), so training SVM and kNN on one batch computes it once.
2. :class:`WaveletStatistics` -- each series -> 3-level ``db2`` wavelet decomposition (PyWavelets) -> rms, std
   and skewness of the series and of each of its 4 coefficient arrays (cA3, cD3, cD2, cD1): 15 per series.
3. :class:`InfoGainSelector` -- keep the ``k`` features of highest information gain (mutual information with
   the class: scikit-learn's ``mutual_info_classif`` estimate, seeded, computed by sorting in
   :func:`fusion.mutual_info.mutual_info_continuous`).
4. :class:`SOMProjection` -- "SOM to 5": a 1 x 5 self-organising map (MiniSom) clusters the selected
   features by correlation; each of the 5 groups gives its first principal component.

Steps 2-4 take and give plain 2-D arrays and pass scikit-learn's ``parametrize_with_checks``; the only check
not run is ``check_array_api_input``, which skips itself unless ``SCIPY_ARRAY_API`` is set (these
transformers use NumPy, PyWavelets and MiniSom, not the array API). Bad 2-D input raises scikit-learn's
``ValueError`` (what its checks require); batch-level input errors are :class:`DatasetError`.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import warnings
import weakref
from collections import OrderedDict

import numpy as np
import pywt
from minisom import MiniSom
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.feature_selection import SelectorMixin
from sklearn.utils.validation import check_is_fitted, validate_data
from threadpoolctl import threadpool_limits

from fusion.contourlet import rescale_exponent, subband_std
from fusion.cues import check_cue, cue_width, kinesthetic_cues
from fusion.mutual_info import mutual_info_continuous
from perception.errors import DatasetError
from tactile.explore import SequenceBatch

log = logging.getLogger(__name__)

#: Directional subbands of the finest contourlet scale (4 DFB levels).
DFB_LEVELS = 4
N_SUBBANDS = 2**DFB_LEVELS
#: Statistics per coefficient array, in output order.
STATISTICS = ("rms", "std", "skew")

# Contourlet std per frame, keyed by the batch object (weakly: dropped with the batch).
_CONTOURLET_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


# ------------------------------------------------------------------------------------ sequences
def n_series(cue: str) -> int:
    """Series per sequence for ``cue``: 16 subbands + the cue's channels (19 for normals, 22 invariant)."""
    return N_SUBBANDS + cue_width(cue)


def contourlet_std(batch: SequenceBatch) -> np.ndarray:
    """(S, P, 16) std of the finest contourlet subbands of every frame of ``batch`` (frame units, mm), cached.

    The cache holds one result per live batch object; it assumes the batch's frames are not changed in place.

    Raises:
        DatasetError: NaN/Inf frames or odd taxel rows/cols.
    """
    cached = _CONTOURLET_CACHE.get(batch)
    if cached is not None and cached[0] is batch.frames:
        return cached[1]
    log.debug("contourlet features of %d frames", batch.frames.shape[0] * batch.frames.shape[1])
    std = subband_std(batch.frames, levels=DFB_LEVELS)
    std.setflags(write=False)
    _CONTOURLET_CACHE[batch] = (batch.frames, std)
    return std


def sequence_features(batch: SequenceBatch, cue: str = "invariant") -> np.ndarray:
    """(S, F * P) float64 series of every sequence, series-major: 16 subband stds then the cue's channels.

    Raises:
        DatasetError: unknown cue, NaN/Inf in the batch, odd taxel rows/cols.
    """
    check_cue(cue)
    if not isinstance(batch, SequenceBatch):
        raise DatasetError(f"sequence_features: expected a SequenceBatch, got {type(batch).__name__}")
    cues = kinesthetic_cues(batch, cue).astype(np.float64)
    if not np.isfinite(cues).all():
        raise DatasetError(f"sequence_features: the {cue!r} cues contain NaN or Inf")
    series = np.concatenate([contourlet_std(batch), cues], axis=-1)  # (S, P, F)
    return np.ascontiguousarray(series.transpose(0, 2, 1)).reshape(len(batch), -1)


class SequenceSeries(TransformerMixin, BaseEstimator):
    """Front step: SequenceBatch (or dataset / store path) -> (S, F * P) series (see :func:`sequence_features`).

    Stateless. Takes batches only, so scikit-learn's random-array estimator checks do not apply to it.
    """

    def __init__(self, cue: str = "invariant"):
        self.cue = cue

    def fit(self, X, y=None):
        check_cue(self.cue)
        return self

    def transform(self, X) -> np.ndarray:
        from fusion.base import as_batch

        return sequence_features(as_batch(X), self.cue)

    def __sklearn_is_fitted__(self) -> bool:
        return True


# ------------------------------------------------------------------------------------ statistics
def safe_skew(a: np.ndarray, axis: int = -1) -> np.ndarray:
    """Sample skewness (biased, as ``scipy.stats.skew``) along ``axis``; 0 for a constant series, never NaN."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape[axis]:
        # Skewness does not depend on scale: series beyond 2**256 (or below 2**-256) are scaled by a power of two
        # (exact), so that their cubes cannot overflow (NaN from 1e103 on) or underflow.
        a = np.ldexp(a, -rescale_exponent(np.max(np.abs(a), axis=axis, keepdims=True)))
    centred = a - a.mean(axis=axis, keepdims=True)
    m2 = np.mean(centred**2, axis=axis)
    m3 = np.mean(centred**3, axis=axis)
    scale = np.max(np.abs(a), axis=axis) if a.shape[axis] else np.zeros(m2.shape)
    # A series is constant when its spread is at rounding level of its values: no shape to measure.
    flat = np.sqrt(m2) <= 1e-10 * scale + np.finfo(np.float64).tiny
    with np.errstate(divide="ignore", invalid="ignore"):
        skew = m3 / np.where(flat, 1.0, m2) ** 1.5
    return np.where(flat, 0.0, skew)


def _statistics(a: np.ndarray) -> np.ndarray:
    """(..., 3) rms, std and skewness along the last axis."""
    return np.stack([np.sqrt(np.mean(a**2, axis=-1)), a.std(axis=-1), safe_skew(a)], axis=-1)


class WaveletStatistics(TransformerMixin, BaseEstimator):
    """(n, F * P) series, series-major -> (n, F * 15): rms, std, skewness of each series and of its wavelet levels.

    Parameters:
        n_series: F, how many series each row holds (the row length must be a multiple).
        wavelet: PyWavelets wavelet name (the paper's ``db2``).
        level: decomposition levels (3): coefficient arrays cA_level, cD_level, ..., cD1.

    Series shorter than the decomposition needs are still decomposed (PyWavelets' boundary-effect warning
    is silenced: with the paper's 25 probes and db2, 3 levels is the maximum and no warning arises).
    """

    def __init__(self, n_series: int = 1, wavelet: str = "db2", level: int = 3):
        self.n_series = n_series
        self.wavelet = wavelet
        self.level = level

    def fit(self, X, y=None):
        X = validate_data(self, X, dtype=np.float64)
        self._check_layout(X.shape[1])
        return self

    def _check_layout(self, n_features: int) -> None:
        if int(self.n_series) < 1 or n_features % int(self.n_series):
            raise ValueError(
                f"WaveletStatistics: {n_features} features is not a whole number of {self.n_series} series"
            )
        if int(self.level) < 1:
            raise ValueError(f"WaveletStatistics: level must be >= 1, got {self.level}")
        pywt.Wavelet(self.wavelet)  # raises ValueError for an unknown name

    def transform(self, X) -> np.ndarray:
        check_is_fitted(self)
        X = validate_data(self, X, dtype=np.float64, reset=False)
        series = X.reshape(len(X), int(self.n_series), -1)
        # Series beyond 2**256 (or below 2**-256) scaled by a power of two (exact): squares of values beyond 1e154
        # overflowed to Inf / NaN. rms and std scale back; skewness does not depend on scale.
        exponent = rescale_exponent(np.max(np.abs(series), axis=-1, keepdims=True))
        unit = np.ldexp(series, -exponent)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Level value of", category=UserWarning)
            coefficients = pywt.wavedec(unit, self.wavelet, level=int(self.level), axis=-1)
        stats = np.stack([_statistics(a) for a in [unit, *coefficients]], axis=2)  # (n, F, arrays, 3)
        with np.errstate(over="ignore"):  # overflow is caught just below
            stats[..., :2] = np.ldexp(stats[..., :2], exponent[..., None])
        if not np.isfinite(stats).all():
            raise ValueError("WaveletStatistics: the rms of series this large exceeds float64; rescale the input")
        return stats.reshape(len(X), -1)  # per series: [series, cA, cD...] x stats

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        check_is_fitted(self)
        arrays = ["series", f"cA{self.level}"] + [f"cD{j}" for j in range(int(self.level), 0, -1)]
        return np.array(
            [f"s{f}_{a}_{s}" for f in range(int(self.n_series)) for a in arrays for s in STATISTICS], dtype=object
        )


# ------------------------------------------------------------------------------------ selection
#: Information gains computed lately, by the digest of their inputs (see :func:`information_gain`).
_GAIN_CACHE: OrderedDict[bytes, np.ndarray] = OrderedDict()
_GAIN_CACHE_SIZE = 16
_GAIN_LOCK = threading.Lock()


def _gain_key(X: np.ndarray, y: np.ndarray, n_neighbors: int, random_state: int) -> bytes:
    """A digest of the estimate's inputs. ``y`` enters as its class indices in sorted order (the estimator
    sees no more of it; an object array's own bytes would be pointers)."""
    h = hashlib.blake2b(digest_size=20)
    classes = np.unique(y, return_inverse=True)[1].astype(np.int64)
    for a in (np.ascontiguousarray(X, dtype=np.float64), np.ascontiguousarray(classes)):
        h.update(repr((a.dtype.str, a.shape)).encode())
        h.update(a.data)
    h.update(repr((int(n_neighbors), int(random_state))).encode())
    return h.digest()


def information_gain(X, y, n_neighbors: int = 3, random_state: int = 0) -> np.ndarray:
    """(n_features,) mutual information (nats) of each column of ``X`` with the labels ``y``, seeded: the floats
    of ``sklearn.feature_selection.mutual_info_classif``, from :func:`fusion.mutual_info.mutual_info_continuous`
    (7-18 times faster here: benchmarks/information_gain.py). All zeros when every class has a single sample.
    The few neighbour searches it leaves to scikit-learn (classes of under ``2 * n_neighbors + 2`` samples) are
    tiny: their OpenMP threads would cost more than they save, so they run on one.

    The last ``_GAIN_CACHE_SIZE`` results are kept by a digest of (X, y, n_neighbors, random_state): a pipeline
    search fits the same selection on the same inner fold once per candidate, and the estimate is a pure
    function of those inputs (seeded), so a repeat returns a copy of the same bytes instead of recomputing.
    """
    X, y = np.asarray(X), np.asarray(y)
    _, counts = np.unique(y, return_counts=True)
    if counts.max() < 2:  # the estimator ignores single-sample classes; with nothing left, nothing is measurable
        log.warning("information gain: every class has a single sample; all features score 0")
        return np.zeros(np.shape(X)[1])
    # Only a seeded estimate is a pure function of its inputs (random_state None or a RandomState is not).
    seeded = isinstance(random_state, (int, np.integer)) and not isinstance(random_state, bool)
    key = _gain_key(X, y, n_neighbors, random_state) if seeded else None
    with _GAIN_LOCK:
        if key is not None and key in _GAIN_CACHE:
            _GAIN_CACHE.move_to_end(key)
            return _GAIN_CACHE[key].copy()
    with threadpool_limits(limits=1, user_api="openmp"):
        gain = mutual_info_continuous(X, y, n_neighbors=n_neighbors, random_state=random_state)
    if key is None:
        return gain
    with _GAIN_LOCK:
        _GAIN_CACHE[key] = gain.copy()
        while len(_GAIN_CACHE) > _GAIN_CACHE_SIZE:
            _GAIN_CACHE.popitem(last=False)
    return gain


class InfoGainSelector(SelectorMixin, BaseEstimator):
    """Keep the ``k`` features of highest information gain with the class (all if there are fewer).

    Information gain of a continuous feature is its mutual information with the label, estimated by
    ``mutual_info_classif`` (k-nearest-neighbour estimator, ``n_neighbors``; seeded by ``random_state``; see
    :func:`information_gain`).
    Ties keep the earlier feature. Fitted: ``scores_`` (nats), ``support_``.
    """

    def __init__(self, k: int = 40, n_neighbors: int = 3, random_state: int = 0):
        self.k = k
        self.n_neighbors = n_neighbors
        self.random_state = random_state

    def fit(self, X, y):
        X, y = validate_data(self, X, y, dtype=np.float64)
        if int(self.k) < 1:
            raise ValueError(f"InfoGainSelector: k must be >= 1, got {self.k}")
        if len(X) < 2:
            raise ValueError(f"InfoGainSelector: n_samples = {len(X)}; mutual information needs at least 2 samples")
        neighbours = max(1, min(int(self.n_neighbors), len(X) - 1))
        self.scores_ = information_gain(X, y, neighbours, self.random_state)
        order = np.argsort(-self.scores_, kind="stable")
        self.support_ = np.zeros(X.shape[1], dtype=bool)
        self.support_[order[: int(self.k)]] = True
        return self

    def _get_support_mask(self) -> np.ndarray:
        check_is_fitted(self)
        return self.support_

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.target_tags.required = True
        return tags


# ----------------------------------------------------------------------------------------- SOM
SOM_OUTPUTS = ("pc1", "best", "mean")


def _first_component(z: np.ndarray) -> np.ndarray:
    """Unit loading vector of the first principal component of centred columns ``z`` (largest entry > 0)."""
    if z.shape[1] == 1:
        return np.ones(1)
    _, _, vt = np.linalg.svd(z, full_matrices=False)
    v = vt[0]
    return v if v[np.argmax(np.abs(v))] > 0 else -v  # fix the SVD's arbitrary sign: same bytes every run


class SOMProjection(TransformerMixin, BaseEstimator):
    """"SOM to 5": cluster the *features* on a 1 x ``n_units`` self-organising map (MiniSom), one output per unit.

    Each input feature is a point of the map's input space: its standardised values over the training
    samples, divided by sqrt(n) so that the distance between two features is sqrt(2 (1 - correlation)).
    The map (Gaussian neighbourhood ``sigma`` in map units, ``learning_rate``, ``n_iterations`` updates in
    a seeded random order, prototypes drawn among the features) groups correlated, redundant features on
    one unit; every feature joins its best-matching unit, and a unit left empty takes the feature nearest
    its prototype among those not yet representing a unit. Output ``j`` per sample:

    - ``output="pc1"`` (default): the first principal component of group ``j``'s standardised features
      (unit loading vector, sign such that its largest entry is positive; a one-feature group is the feature);
    - ``output="best"``: the standardised feature of highest information gain in group ``j`` (mutual
      information with ``y``, as :class:`InfoGainSelector`; without ``y``: the one nearest the prototype);
    - ``output="mean"``: the mean of the standardised features of group ``j``.

    Why features and not samples: a 1 x 5 map of the *samples* describing each sample by its 5 distances
    to the prototypes measured far below PCA to 5 (catalogue, blind, 10 classes x 4 objects x 30 contours,
    80/20 by sequence, 4 splits: SVM 57 % vs 74 %, kNN 54 % vs 68 %). Grouping features, with normals as
    the cue, measured at least as accurate as PCA to 5 (4 splits each; SVM / kNN): blind 75.8 / 70.4 % vs
    74.3 / 67.7 %, guided (10 x 3 x 30) 81.5 / 74.7 % vs 80.0 / 74.2 %; with the pose-invariant cue PCA
    was better (blind 93.0 / 88.2 % vs 89.8 / 85.9 %).
    Fewer input features than units gives one output per feature. Fitted: ``groups_`` (unit of each input
    feature), ``representatives_`` (per group: most informative with "best", else nearest its prototype), ``loadings_`` (n_features, units):
    output = standardised X @ loadings_, ``mean_``, ``scale_``, ``prototypes_``.
    """

    def __init__(
        self,
        n_units: int = 5,
        output: str = "pc1",
        sigma: float = 1.0,
        learning_rate: float = 0.5,
        n_iterations: int = 5000,
        n_neighbors: int = 3,
        random_state: int = 0,
    ):
        self.n_units = n_units
        self.output = output
        self.sigma = sigma
        self.learning_rate = learning_rate
        self.n_iterations = n_iterations
        self.n_neighbors = n_neighbors
        self.random_state = random_state

    def fit(self, X, y=None):
        X = validate_data(self, X, dtype=np.float64)
        if int(self.n_units) < 1 or int(self.n_iterations) < 1:
            raise ValueError(
                f"SOMProjection: n_units and n_iterations must be >= 1, got {self.n_units}, {self.n_iterations}"
            )
        if self.output not in SOM_OUTPUTS:
            raise ValueError(f"SOMProjection: output must be one of {SOM_OUTPUTS}, got {self.output!r}")
        n, n_features = X.shape
        units = min(int(self.n_units), n_features)
        self.mean_ = X.mean(axis=0)
        std = X.std(axis=0)
        self.scale_ = np.where(std > 1e-12 * (np.abs(self.mean_) + 1.0), std, 1.0)  # constant feature: keep 0
        points = ((X - self.mean_) / self.scale_).T / np.sqrt(n)  # (features, samples), unit norm
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # MiniSom: "sigma is too high" for a 1-row map
            som = MiniSom(
                1, units, n, sigma=float(self.sigma), learning_rate=float(self.learning_rate),
                random_seed=self.random_state,
            )
            som.random_weights_init(points)
            som.train(points, int(self.n_iterations), random_order=True)
        self.prototypes_ = som.get_weights().reshape(units, n)
        distance = np.linalg.norm(points[:, None, :] - self.prototypes_[None], axis=-1)  # (features, units)
        groups = distance.argmin(axis=1)
        if y is not None and self.output == "best" and n > 1:
            neighbours = max(1, min(int(self.n_neighbors), n - 1))
            gain = information_gain(X, y, neighbours, self.random_state)
        else:
            gain = -distance[np.arange(n_features), groups]  # nearest to its prototype
        representatives = np.full(units, -1)
        for j in range(units):
            members = np.flatnonzero(groups == j)
            if len(members):
                representatives[j] = members[np.argmax(gain[members])]
        for j in np.flatnonzero(representatives < 0):  # an empty unit borrows its nearest free feature
            free = np.setdiff1d(np.arange(n_features), representatives)
            pick = free[np.argmin(distance[free, j])]
            groups[pick], representatives[j] = j, pick
        self.groups_, self.representatives_ = groups, representatives
        z = (X - self.mean_) / self.scale_
        self.loadings_ = np.zeros((n_features, units))  # output = z @ loadings_
        for j in range(units):
            members = np.flatnonzero(groups == j)
            if self.output == "best":
                self.loadings_[representatives[j], j] = 1.0
            elif self.output == "mean":
                self.loadings_[members, j] = 1.0 / len(members)
            else:
                self.loadings_[members, j] = _first_component(z[:, members])
        return self

    def transform(self, X) -> np.ndarray:
        check_is_fitted(self)
        X = validate_data(self, X, dtype=np.float64, reset=False)
        return ((X - self.mean_) / self.scale_) @ self.loadings_

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        check_is_fitted(self)
        return np.array([f"som_{self.output}{j}" for j in range(len(self.representatives_))], dtype=object)


__all__ = [
    "DFB_LEVELS",
    "N_SUBBANDS",
    "InfoGainSelector",
    "SOMProjection",
    "SequenceSeries",
    "WaveletStatistics",
    "contourlet_std",
    "information_gain",
    "n_series",
    "safe_skew",
    "sequence_features",
]
