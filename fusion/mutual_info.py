"""Mutual information of continuous features with a class label: scikit-learn's estimate, computed by sorting.

``sklearn.feature_selection.mutual_info_classif`` (Ross 2014, the k-nearest-neighbour estimator for a continuous
variable and a discrete one) builds, for every feature, a neighbour tree per class and one over all samples, and
validates each of them in Python: on the training sets here (hundreds of features, thousands of sequences) that
overhead is most of the work, and the information-gain step was a fifth of ``reproduce --quick``'s CPU time.

In one dimension both of its neighbour questions have sorted answers:

- the distance from a sample to its k-th nearest neighbour of the same class is the k-th smallest of the gaps to
  the k samples on either side of it in that class's sorted order;
- the samples the all-samples tree counts within that radius form one run of the sorted feature around the sample
  (the tree's test, ``(x_j - x_i)**2 <= r**2`` in floating point, is monotone along each side), whose ends a binary
  search finds and the same test settles.

:func:`mutual_info_continuous` applies scikit-learn's own preprocessing (scaling, seeded jitter) and then these
answers, so its estimates are scikit-learn's to the bit (``tests/fusion/test_mutual_info.py`` compares them on
random, tied, tiny and real feature sets); a class too small for scikit-learn's tree (it then compares squared
distances expanded as ``x**2 - 2 x y + y**2``) gets its radii from scikit-learn itself.
"""

from __future__ import annotations

from numbers import Integral

import numpy as np
from scipy.sparse import issparse
from scipy.special import digamma
from sklearn.neighbors import NearestNeighbors
from sklearn.preprocessing import scale
from sklearn.utils import check_random_state
from sklearn.utils.multiclass import check_classification_targets
from sklearn.utils.validation import check_X_y


def mutual_info_continuous(X, y, n_neighbors: int = 3, random_state=None) -> np.ndarray:
    """(n_features,) mutual information (nats, >= 0) of each column of the dense ``X`` (n_samples, n_features)
    with the class labels ``y``: ``mutual_info_classif(X, y, discrete_features=False, n_neighbors=n_neighbors,
    random_state=random_state)``, the same floats.

    Raises:
        ValueError: a sparse, non-finite or empty ``X``, continuous labels, ``n_neighbors`` not an integer >= 1 (as
            scikit-learn refuses them), or no class with two samples (nothing to estimate from).
    """
    if issparse(X):
        raise ValueError("mutual_info_continuous takes a dense X; a sparse matrix holds no continuous features here")
    check_classification_targets(y)
    X, y = check_X_y(X, y, y_numeric=False)
    if isinstance(n_neighbors, bool) or not isinstance(n_neighbors, Integral) or n_neighbors < 1:
        raise ValueError(f"n_neighbors must be an integer >= 1, got {n_neighbors!r}")
    n_samples, n_features = X.shape
    rng = check_random_state(random_state)
    # scikit-learn's preprocessing, step for step: unit variance, then jitter that breaks ties, drawn in one go. The
    # column mask stays: indexing with it lays the copy out in another order, and the variances sum in that order.
    every = np.ones(n_features, dtype=bool)
    X = X.astype(np.float64, copy=True)
    with np.errstate(over="ignore", invalid="ignore"):  # an overflowing variance is refused below, in words
        X[:, every] = scale(X[:, every], with_mean=False, copy=False)
        means = np.maximum(1, np.mean(np.abs(X[:, every]), axis=0))
    X[:, every] += 1e-10 * means * rng.standard_normal(size=(n_samples, n_features))
    if not np.isfinite(X).all():  # a variance beyond float64 scales a column to NaN; scikit-learn's trees refuse it
        raise ValueError("X contains NaN or infinity after scaling to unit variance (a column's variance overflows "
                         "float64)")
    classes, codes = np.unique(y, return_inverse=True)
    members = [np.flatnonzero(codes == c) for c in range(len(classes))]
    if max(len(m) for m in members) < 2:
        raise ValueError(f"every one of the {len(classes)} classes has a single sample: the estimate needs two of a class")
    # What does not depend on the feature, once: each class's neighbour count k and the estimate's label terms,
    # summed in scikit-learn's order (left to right), so that only the radius counts' term is left per feature.
    k_all, label_counts = np.empty(n_samples), np.empty(n_samples)
    for idx in members:
        k_all[idx] = min(int(n_neighbors), len(idx) - 1)
        label_counts[idx] = len(idx)
    keep = label_counts > 1  # samples alone in their class do not count
    label_terms = (digamma(int(keep.sum())) + np.mean(digamma(k_all[keep]))
                   - np.mean(digamma(label_counts[keep])))
    classes_k = [(idx, int(k_all[idx[0]])) for idx in members if len(idx) > 1]
    columns = np.ascontiguousarray(X.T)
    return np.array([max(0, label_terms - np.mean(digamma(_radius_counts(x, classes_k, keep)))) for x in columns])


def _radius_counts(x: np.ndarray, classes_k: list[tuple[np.ndarray, int]], keep: np.ndarray) -> np.ndarray:
    """For one continuous column ``x`` (n,): the samples within each kept sample's k-th same-class neighbour
    distance (``classes_k``: each class of two or more, its sample indices and k), over the kept samples."""
    radius = np.empty(len(x))
    for idx, k in classes_k:
        radius[idx] = np.nextafter(_kth_neighbour_distance(x[idx], k), 0)
    return _count_within(x[keep], radius[keep])


def _kth_neighbour_distance(v: np.ndarray, k: int) -> np.ndarray:
    """(m,) distance from each value of ``v`` (m,) to its k-th nearest other value, as scikit-learn's
    ``NearestNeighbors(n_neighbors=k).fit(v).kneighbors()`` reports it."""
    m = len(v)
    if k >= m // 2:
        # scikit-learn searches by brute force here, with distances expanded through a dot product: ask it.
        return NearestNeighbors(n_neighbors=k).fit(v[:, None]).kneighbors()[0][:, -1]
    order = np.argsort(v, kind="stable")
    s = v[order]
    gaps = np.full((2 * k, m), np.inf)
    for j in range(1, k + 1):
        d = s[j:] - s[:-j]  # |x_a - x_b| exactly as the tree's sqrt((x_a - x_b)**2) gives it
        gaps[j - 1, j:] = d  # to the j-th value below
        gaps[k + j - 1, :-j] = d  # to the j-th value above
    kth = np.empty(m)
    kth[order] = np.partition(gaps, k - 1, axis=0)[k - 1]
    return kth


def _count_within(x: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(n,) int: how many values x_j satisfy ``(x_j - x_i)**2 <= radius_i**2`` in float64 for each i, the count
    scikit-learn's ``KDTree(x).query_radius(x, radius, count_only=True)`` returns (itself included)."""
    s = np.sort(x)
    n = len(s)
    r2 = radius * radius

    def inside(j, mask):  # the tree's test for positions j where mask, False elsewhere
        out = np.zeros(len(j), dtype=bool)
        jj = j[mask]
        d = s[jj] - x[mask]
        out[mask] = d * d <= r2[mask]
        return out

    hi = np.searchsorted(s, x + radius, side="right")  # first position past the run, up to rounding
    lo = np.searchsorted(s, x - radius, side="left")  # first position of the run, up to rounding
    # Move each end until the test holds just inside it and fails just outside (the test is monotone on either
    # side of x_i, and x_i itself always passes, so each end stops within a few positions of its estimate).
    for _ in range(n + 1):  # each end moves one way only, so n + 1 rounds always suffice
        grow = inside(hi, hi < n)
        shrink = ~inside(hi - 1, hi > 0) & (hi > 0)
        if not (grow.any() or shrink.any()):
            break
        hi = hi + grow - shrink
    for _ in range(n + 1):
        grow = inside(lo - 1, lo > 0)
        shrink = ~inside(lo, lo < n) & (lo < n)
        if not (grow.any() or shrink.any()):
            break
        lo = lo - grow + shrink
    return hi - lo


__all__ = ["mutual_info_continuous"]
