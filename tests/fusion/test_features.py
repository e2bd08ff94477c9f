"""Conventional features: series from batches, wavelet statistics vs PyWavelets/scipy, selection, SOM, sklearn checks."""

from __future__ import annotations

import warnings
from functools import cache

import numpy as np
import pytest
import pywt
from scipy.stats import skew
from sklearn.decomposition import PCA
from sklearn.feature_selection import mutual_info_classif
from sklearn.utils.estimator_checks import parametrize_with_checks

from fusion.contourlet import contourlet
from fusion.features import (
    InfoGainSelector,
    SequenceSeries,
    SOMProjection,
    WaveletStatistics,
    contourlet_std,
    n_series,
    safe_skew,
    sequence_features,
)
from perception.errors import DatasetError, InvalidArgumentError
from perception.shapes import CLASSES, make_object
from tactile.explore import SequenceBatch
from tactile.sampling import explore_object
from tactile.sensor import FSRSensor

CLASS_SUBSET = CLASSES[:4]


@cache
def small_batch(rows: int = 16, cols: int = 16) -> SequenceBatch:
    """4 classes x 2 objects x 10 blind contours of 25 probes, a 16 x 16 pad (shared with test_conventional)."""
    sensor = FSRSensor(rows=rows, cols=cols)
    sequences = []
    for c, name in enumerate(CLASS_SUBSET):
        for o in range(2):
            model = make_object(name, 100 * c + o)
            sequences += explore_object(model, "blind", 10, sensor=sensor, seed=10 * c + o)
    return SequenceBatch.from_sequences(sequences, CLASS_SUBSET, sensor_spec=sensor.spec())


# ------------------------------------------------------------------------------------- series
def test_sequence_features_layout_and_cache():
    batch = small_batch()
    s, p = len(batch), batch.n_probes
    feats = sequence_features(batch, "normals")
    assert feats.shape == (s, 19 * p) and n_series("normals") == 19 and n_series("invariant") == 22
    series = feats.reshape(s, 19, p)
    # Series 0..15: the std of each finest contourlet subband of each frame (direct transform as reference).
    direct = contourlet(batch.frames[:3], levels=(3, 4)).bands[-1].std(axis=(-2, -1))  # (3, P, 16)
    np.testing.assert_allclose(series[:3, :16], direct.transpose(0, 2, 1), rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(series[:, 16:], batch.normals.transpose(0, 2, 1), rtol=1e-6)
    assert sequence_features(batch, "invariant").shape == (s, 22 * p)
    assert contourlet_std(batch) is contourlet_std(batch)  # computed once per batch
    assert np.array_equal(SequenceSeries("normals").fit(batch).transform(batch), feats)


def test_sequence_features_bad_input():
    batch = small_batch()
    with pytest.raises(InvalidArgumentError, match="unknown kinesthetic cue"):
        sequence_features(batch, "colour")
    with pytest.raises(DatasetError, match="SequenceBatch"):
        sequence_features(np.zeros((2, 25, 16, 16)))
    bad = batch.subset(np.arange(4))
    bad.frames = bad.frames.copy()
    bad.frames[1, 3, 2, 2] = np.nan
    with pytest.raises(DatasetError, match="NaN or Inf"):
        sequence_features(bad)
    with pytest.raises(DatasetError, match="NaN or Inf"):
        SequenceSeries().transform(bad)


# ---------------------------------------------------------------------------------- statistics
def test_safe_skew_matches_scipy_and_is_zero_on_constants():
    rng = np.random.default_rng(0)
    a = rng.gamma(2.0, size=(6, 25))
    np.testing.assert_allclose(safe_skew(a), skew(a, axis=-1), rtol=1e-12)
    const = np.full((3, 25), 4.2)
    const[1] = 0.0
    const[2] = 1e-300
    out = safe_skew(const)
    assert np.array_equal(out, np.zeros(3))
    assert safe_skew(np.array([0.1 + 1e-17 * i for i in range(8)])) == 0.0  # rounding-level wiggle is flat


def test_wavelet_statistics_against_pywavelets_by_hand():
    rng = np.random.default_rng(1)
    p = 25
    X = rng.standard_normal((4, 3 * p))
    out = WaveletStatistics(n_series=3).fit(X).transform(X)
    assert out.shape == (4, 3 * 15)
    # Hand-assembled reference for sample 2, series 1.
    x = X[2, p : 2 * p]
    arrays = [x, *pywt.wavedec(x, "db2", level=3)]
    assert [len(a) for a in arrays[1:]] == [5, 5, 8, 14]
    ref = np.concatenate([[np.sqrt(np.mean(a**2)), np.std(a), skew(a)] for a in arrays])
    np.testing.assert_allclose(out[2, 15:30], ref, rtol=1e-10)
    names = WaveletStatistics(n_series=3).fit(X).get_feature_names_out()
    assert names[15] == "s1_series_rms" and names[29] == "s1_cD1_skew" and len(names) == 45


def test_wavelet_statistics_constant_series_finite():
    X = np.full((3, 2 * 25), 2.5)
    X[1] = 0.0
    out = WaveletStatistics(n_series=2).fit(X).transform(X)
    assert np.isfinite(out).all()
    # rms of a constant c is |c|, its std 0 and its skewness 0; the detail coefficients of a constant are 0.
    assert out[0, 0] == pytest.approx(2.5) and out[0, 1] == pytest.approx(0.0, abs=1e-12)
    assert np.all(out[:, 2::3] == 0.0)


def test_wavelet_statistics_rejects_bad_layout():
    with pytest.raises(ValueError, match="whole number"):
        WaveletStatistics(n_series=4).fit(np.zeros((3, 10)))


# ----------------------------------------------------------------------------------- selection
def test_info_gain_keeps_the_informative_features():
    rng = np.random.default_rng(2)
    y = np.repeat(np.arange(3), 40)
    X = rng.standard_normal((120, 8))
    X[:, 5] += 3.0 * y  # strongly informative
    X[:, 2] += 1.0 * y  # weakly informative
    sel = InfoGainSelector(k=2, random_state=0).fit(X, y)
    assert sorted(np.flatnonzero(sel.get_support())) == [2, 5]
    np.testing.assert_array_equal(sel.scores_, mutual_info_classif(X, y, n_neighbors=3, random_state=0))
    assert sel.transform(X).shape == (120, 2)
    assert InfoGainSelector(k=50).fit(X, y).transform(X).shape == (120, 8)  # k above the width keeps all
    again = InfoGainSelector(k=2, random_state=0).fit(X, y)
    assert np.array_equal(again.scores_, sel.scores_)  # seeded: same bytes



def test_info_gain_repeats_come_from_the_cache_with_sklearns_bytes(monkeypatch):
    """A repeated (X, y, k, seed) is not estimated again and returns sklearn's own result; changed data, labels
    relabelled into another class order, or another seed are estimated afresh; an unseeded call is never cached."""
    from fusion import features

    rng = np.random.default_rng(7)
    y = np.repeat(np.arange(3), 30)
    X = rng.standard_normal((90, 4)) + y[:, None] * np.array([2.0, 0.0, 0.5, 0.0])
    expected = mutual_info_classif(X, y, n_neighbors=3, random_state=1)
    calls = []
    real = features.mutual_info_continuous
    monkeypatch.setattr(features, "mutual_info_continuous", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(features, "_GAIN_CACHE", type(features._GAIN_CACHE)())
    first = features.information_gain(X, y, 3, 1)
    first[:] = -1.0  # a caller scribbling on its result must not change the cached one
    second = features.information_gain(X.copy(), y.copy(), 3, 1)
    assert len(calls) == 1 and np.array_equal(second, expected)
    features.information_gain(X + 1e-9, y, 3, 1)  # other data
    features.information_gain(X, 2 - y, 3, 1)  # same partition, classes in the other order
    features.information_gain(X, y, 3, 2)  # other seed
    features.information_gain(X, y, 3, None)
    features.information_gain(X, y, 3, None)
    assert len(calls) == 6



def test_info_gain_cache_keys_the_neighbours_copies_hits_and_forgets_the_least_recent(monkeypatch):
    from fusion import features

    rng = np.random.default_rng(0)
    y = np.repeat(np.arange(3), 20)
    X = rng.standard_normal((60, 3)) + y[:, None]
    calls = []
    real = features.mutual_info_continuous
    monkeypatch.setattr(features, "mutual_info_continuous", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(features, "_GAIN_CACHE", type(features._GAIN_CACHE)())
    features.information_gain(X, y, 3, 0)
    assert np.array_equal(features.information_gain(X, y, 5, 0), mutual_info_classif(X, y, n_neighbors=5, random_state=0))
    hit = features.information_gain(X, y, 3, 0)
    hit[:] = -1.0
    assert (features.information_gain(X, y, 3, 0) >= 0).all()
    features.information_gain(X, np.array([f"c{v}" for v in y]), 3, 0)  # the same partition, named: a hit
    assert len(calls) == 2
    for s in range(1, features._GAIN_CACHE_SIZE):
        features.information_gain(X, y, 3, 0)  # keep it the most recently used
        features.information_gain(X, y, 3, 100 + s)
    assert len(features._GAIN_CACHE) == features._GAIN_CACHE_SIZE
    n = len(calls)
    features.information_gain(X, y, 3, 0)
    assert len(calls) == n  # recently used: kept
    features.information_gain(X, y, 5, 0)
    assert len(calls) == n + 1  # the least recently used entry (k = 5) was dropped


def test_info_gain_bytes_do_not_depend_on_the_job_count(monkeypatch):
    """The experiments train with joblib's n_jobs set to every core: the selection must not change with it."""
    import joblib

    from fusion import features

    rng = np.random.default_rng(11)
    y = np.repeat(np.arange(4), 25)
    X = rng.standard_normal((100, 12)) + np.outer(y, np.linspace(0, 1, 12))
    monkeypatch.setattr(features, "_GAIN_CACHE", type(features._GAIN_CACHE)())
    one = features.information_gain(X, y, 3, 0)
    features._GAIN_CACHE.clear()
    with joblib.parallel_config(n_jobs=2):
        two = features.information_gain(X, y, 3, 0)
    assert np.array_equal(one, two)


# ------------------------------------------------------------------------------------------ SOM
def _grouped_features(seed: int = 3):
    """15 features: 3 noisy copies of each of 5 independent signals (column 3 g + c copies signal g)."""
    rng = np.random.default_rng(seed)
    y = np.repeat(np.arange(3), 60)
    latent = rng.standard_normal((180, 5))
    latent[:, 1] += 1.5 * y  # signal 1 carries the class
    noise = np.array([0.1, 0.3, 0.6])  # copy 0 is the cleanest
    X = np.repeat(latent, 3, axis=1) + rng.standard_normal((180, 15)) * np.tile(noise, 5)
    return X * rng.uniform(0.5, 20.0, 15) + rng.uniform(-5, 5, 15), y  # arbitrary units and offsets


def test_som_groups_redundant_features():
    X, y = _grouped_features()
    som = SOMProjection(n_units=5, output="best", random_state=0).fit(X, y)
    # Each unit holds exactly the 3 copies of one signal (feature correlations are ~0.9 within, ~0 across).
    groups = som.groups_.reshape(5, 3)
    assert all(len(set(g)) == 1 for g in groups) and len(set(groups[:, 0])) == 5
    # "best": per group the copy of highest mutual information with y (scikit-learn's estimate as the peer).
    mi = mutual_info_classif(X, y, n_neighbors=3, random_state=0)
    for unit, rep in enumerate(som.representatives_):
        members = np.flatnonzero(som.groups_ == unit)
        assert rep == members[np.argmax(mi[members])]
    z = (X - X.mean(axis=0)) / X.std(axis=0)
    np.testing.assert_allclose(som.transform(X), z[:, som.representatives_], rtol=1e-10)
    # The informative signal's group is represented by its cleanest copy (column 3).
    assert 3 in som.representatives_
    # "mean": the average of each group's standardised features.
    mean = SOMProjection(n_units=5, output="mean", random_state=0).fit(X)
    expected = np.stack([z[:, mean.groups_ == j].mean(axis=1) for j in range(5)], axis=1)
    np.testing.assert_allclose(mean.transform(X), expected, rtol=1e-10)
    # "pc1" (default): each group's first principal component (scikit-learn's PCA as the peer, up to sign).
    pc1 = SOMProjection(n_units=5, random_state=0).fit(X, y)
    out = pc1.transform(X)
    for j in range(5):
        ref = PCA(n_components=1).fit_transform(z[:, pc1.groups_ == j])[:, 0]
        np.testing.assert_allclose(np.abs(out[:, j]), np.abs(ref), rtol=1e-8, atol=1e-10)
    again = SOMProjection(n_units=5, random_state=0).fit(X, y)
    assert np.array_equal(again.transform(X), out)  # seeded: same bytes


def test_som_edge_cases():
    X, y = _grouped_features()
    # Fewer features than units: one output per feature; constant features stay finite (0 after centring).
    few = SOMProjection(n_units=5).fit(X[:, :3], y)
    assert few.transform(X[:, :3]).shape == (180, 3)
    flat = np.ones((10, 6))
    out = SOMProjection(n_units=5, n_iterations=50).fit(flat, np.arange(10) % 2).transform(flat)
    assert out.shape == (10, 5) and np.all(out == 0.0)
    with pytest.raises(ValueError, match="output"):
        SOMProjection(output="distance").fit(X)


# ---------------------------------------------------------------------------- scikit-learn checks
@parametrize_with_checks(
    [WaveletStatistics(), InfoGainSelector(k=2), SOMProjection(n_iterations=50)],
)
def test_sklearn_compatible(estimator, check):
    # check_array_api_input skips itself unless SCIPY_ARRAY_API is set (none of these use the array API).
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check(estimator)
