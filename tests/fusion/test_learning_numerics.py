"""Learning numerics. Constant, duplicate, huge and tiny inputs, a class of one sample:
a clear project exception or finite output checked against a known answer; never a NaN probability.

Already covered elsewhere, not repeated: skewness of constant and rounding-level series and constant
wavelet series (tests/fusion/test_features.py), a SOM fed identical samples (test_som_edge_cases), a constant
tactile video and constant training features through the SVM / kNN and NaN frames refused
(tests/fusion/test_conventional.py::test_constant_video_and_bad_input), every class of one sample
(test_invariant_cue_and_small_training_sets), a CNN trained on all-zero frames and fed 3e38 on an unpooled
8 x 8 grid, NaN refused by the CNN (tests/fusion/test_cnn.py), NaN / Inf frames refused by the contourlet
(tests/fusion/test_contourlet.py::test_bad_frames_raise), NaN / Inf refused by the 2-D transformers
(scikit-learn's estimator checks in test_features.py).
"""

from __future__ import annotations

import numpy as np
import pytest
import pywt
from scipy.ndimage import convolve1d
from scipy.stats import skew

from fusion.cnn import CNNClassifier, pool_frames
from fusion.contourlet import contourlet, icontourlet, lp_filters, subband_std
from fusion.conventional import ConventionalClassifier
from fusion.features import InfoGainSelector, SOMProjection, WaveletStatistics, safe_skew
from perception.errors import DatasetError
from tactile.sensor import FSRSensor
from tests.fusion.test_cnn import make_batch

FAST_CONVENTIONAL = {"som_iterations": 200, "n_select": 20}
FAST_CNN = {"epochs": 2, "batch_size": 8, "progress": False, "threads": 1}
N = 32


# -------------------------------------------------------------------------- constant and duplicate
def test_constant_features_score_zero_and_duplicates_tie_to_the_earlier():
    rng = np.random.default_rng(0)
    y = np.repeat(np.arange(3), 30)
    signal = rng.standard_normal(90) + 1.5 * y
    X = np.column_stack([np.full(90, 4.2), signal, signal, signal, rng.standard_normal(90)])
    selector = InfoGainSelector(k=2, random_state=0).fit(X, y)
    assert selector.scores_[0] == 0.0  # a constant carries no information about anything
    assert selector.scores_[1] == selector.scores_[2] == selector.scores_[3] > selector.scores_[4]
    np.testing.assert_array_equal(np.flatnonzero(selector.get_support()), [1, 2])  # ties keep the earlier


@pytest.mark.parametrize("output", ["pc1", "mean", "best"])
def test_som_fed_identical_features_outputs_the_feature(output):
    rng = np.random.default_rng(1)
    z = rng.standard_normal(40)
    X = np.repeat(3.0 * z[:, None] + 2.0, 10, axis=1)  # ten identical columns
    som = SOMProjection(n_units=5, output=output, n_iterations=200).fit(X, np.arange(40) % 2)
    out = som.transform(X)
    assert out.shape == (40, 5) and np.isfinite(out).all()
    standard = (z - z.mean()) / z.std()
    sizes = np.bincount(som.groups_, minlength=5)
    assert sizes.sum() == 10 and (sizes >= 1).all()  # an empty unit borrows a feature: every output defined
    # By hand: the first principal component of m identical standardised columns is their sum / sqrt(m);
    # their mean, and the best of them, are the column itself.
    factor = np.sqrt(sizes) if output == "pc1" else np.ones(5)
    np.testing.assert_allclose(out, standard[:, None] * factor, rtol=1e-10, atol=1e-12)


# ------------------------------------------------------------------------------ huge and tiny series
@pytest.mark.parametrize("value", [1e300, -1e308, 1e-300, 5e-324, 1.7976931348623157e308])
def test_skewness_of_a_constant_series_of_any_magnitude_is_zero(value):
    assert safe_skew(np.full((2, 25), value)).tolist() == [0.0, 0.0]


@pytest.mark.parametrize("exponent", [-1000, -500, 400, 900, 1000])
def test_skewness_does_not_depend_on_magnitude(exponent):
    series = np.random.default_rng(2).gamma(2.0, size=(4, 25))
    scaled = np.ldexp(series, exponent)  # 2**1000 is 1e301: cubes overflowed to NaN before
    assert np.isfinite(scaled).all() and (scaled != 0).all()
    np.testing.assert_allclose(safe_skew(scaled), skew(series, axis=-1), rtol=1e-12)


@pytest.mark.parametrize("scale", [1e200, 1e-200])
def test_wavelet_statistics_of_huge_and_tiny_series_against_pywavelets(scale):
    rng = np.random.default_rng(3)
    p = 25
    X = rng.standard_normal((3, 2 * p))
    out = WaveletStatistics(n_series=2).fit(X * scale).transform(X * scale)
    assert np.isfinite(out).all()
    # By hand for sample 1, series 1 on the unscaled data: rms and std scale, skewness does not.
    x = X[1, p:]
    arrays = [x, *pywt.wavedec(x, "db2", level=3)]
    ref = np.concatenate([[np.sqrt(np.mean(a**2)) * scale, np.std(a) * scale, skew(a)] for a in arrays])
    np.testing.assert_allclose(out[1, 15:30], ref, rtol=1e-10)


@pytest.mark.filterwarnings("ignore:invalid value encountered in reduce")  # scikit-learn's finiteness check
def test_wavelet_statistics_beyond_float64_raise_a_clear_error():
    X = np.tile([1.7e308, -1.7e308], 25)[None]  # its wavelet details exceed the largest float64
    with pytest.raises(ValueError, match="exceeds float64"):
        WaveletStatistics(n_series=1).fit(X).transform(X)


# --------------------------------------------------------------------------------------- contourlet
@pytest.mark.parametrize("value", [7.0, -1e300, 1e-300])
def test_contourlet_of_a_constant_image_is_all_lowpass(value):
    coeffs = contourlet(np.full((N, N), value))
    # The 9/7 low-pass taps sum to sqrt 2 per axis: each pyramid level doubles a constant, which it predicts
    # exactly, so every directional subband of both levels is zero and the low-pass image is 4 x the value.
    for band in coeffs.bands:
        assert np.abs(band).max() <= 1e-10 * abs(value)
    np.testing.assert_allclose(coeffs.lowpass, 4.0 * value, rtol=1e-12)
    assert (subband_std(np.full((2, N, N), value)) <= 1e-10 * abs(value)).all()


def test_contourlet_of_a_constant_beyond_float64_raises():
    with pytest.raises(DatasetError, match="exceed float64"):
        contourlet(np.full((N, N), 1.7e308))  # its low-pass image would be 6.8e308


def _scipy_band_pass(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pyramid level by scipy: periodic 9/7 filtering, decimation and prediction by hand."""
    h, g = lp_filters()
    smooth = convolve1d(convolve1d(x, h, axis=0, mode="wrap"), h, axis=1, mode="wrap")
    up = np.zeros_like(x)
    up[::2, ::2] = smooth[::2, ::2]
    return smooth[::2, ::2], x - convolve1d(convolve1d(up, g, axis=0, mode="wrap"), g, axis=1, mode="wrap")


@pytest.mark.parametrize("amplitude", [1.0, 1e300, 1e-300])
def test_contourlet_of_a_single_spike_keeps_each_band_pass_energy(amplitude):
    spike = np.zeros((N, N))
    spike[4, 8] = amplitude
    coeffs = contourlet(spike)
    coarse, fine = _scipy_band_pass(spike / amplitude)
    _, middle = _scipy_band_pass(coarse)
    # Tight frame: the directional subbands of a level carry exactly the energy of its band-pass image.
    for band, reference in zip(coeffs.bands, (middle, fine)):
        assert np.isfinite(band).all()
        energy = ((band / amplitude) ** 2).sum()
        assert energy == pytest.approx((reference**2).sum(), rel=1e-10)
    np.testing.assert_allclose(icontourlet(coeffs) / amplitude, spike / amplitude, atol=1e-12)
    direct = (coeffs.bands[-1] / amplitude).std(axis=(-2, -1))
    np.testing.assert_allclose(subband_std(spike) / amplitude, direct, rtol=1e-9)


# ---------------------------------------------------------------------------------------------- CNN
def test_cnn_pooling_huge_frames_stays_finite():
    frames = np.full((2, 3, N, N), 3e38, dtype=np.float32)
    frames[1] *= -1
    pooled = pool_frames(frames, 16).numpy()  # float32 sums of 4 such readings overflowed to Inf
    np.testing.assert_array_equal(pooled, frames[:, :, ::2, ::2])


def test_cnn_trained_on_huge_frames_and_constant_cues_predicts_finite_probabilities():
    spec = FSRSensor(rows=N, cols=N).spec()
    train = make_batch(n_per_class=3, probes=3, grid=(N, N), spec=spec)
    train.frames *= np.float32(1e30)
    train.normals[:] = np.float32([0.0, 0.6, 0.8])  # a constant cue: no spread to divide by
    model = CNNClassifier(cue="normals", **{**FAST_CNN, "epochs": 1}).fit(train)
    blocks = train.frames.astype(np.float64).reshape(len(train), 3, 16, 2, 16, 2).mean(axis=(3, 5))
    assert model.frame_mean_ == pytest.approx(blocks.mean(), rel=1e-6)
    assert model.frame_std_ == pytest.approx(blocks.std(), rel=1e-5)
    np.testing.assert_array_equal(model.cue_std_, 1.0)
    np.testing.assert_allclose(model.cue_mean_, [0.0, 0.6, 0.8], rtol=1e-6)
    for fill in (0.0, 3e38, -3e38):
        probe = make_batch(n_per_class=1, probes=3, grid=(N, N), spec=spec)
        probe.frames[:] = fill
        for proba in model.predict_proba_modalities(probe).values():  # raw softmax, not renormalised
            assert np.isfinite(proba).all() and np.allclose(proba.sum(axis=1), 1.0)


# ------------------------------------------------------------------------------ a class of one sample
@pytest.fixture(scope="module")
def one_of_a_class():
    """A batch of 3 classes x 6 sequences, a training part where class 2 has a single sequence, its index
    in the batch, and a 1-nearest-neighbour classifier trained on that part."""
    batch = make_batch(n_per_class=6, probes=25, grid=(8, 8))
    single = int(np.flatnonzero(batch.labels == 2)[0])
    train = batch.subset(np.r_[np.flatnonzero(batch.labels != 2), single])
    knn = ConventionalClassifier(kind="knn", n_neighbors=1, **FAST_CONVENTIONAL).fit(train)
    return batch, train, single, knn


def test_a_class_of_one_sample(one_of_a_class):
    batch, train, single, knn = one_of_a_class
    # 1-nearest neighbour answers a training sequence's own class: the single one's too, with certainty.
    np.testing.assert_array_equal(knn.predict_proba(batch.subset([single])), [[0.0, 0.0, 1.0]])
    with pytest.raises(DatasetError, match="at least 2 sequences per class"):
        ConventionalClassifier(kind="svm", **FAST_CONVENTIONAL).fit(train)
    cnn = CNNClassifier(**{**FAST_CNN, "epochs": 1}, val_fraction=0.5).fit(train)
    labels = np.searchsorted(cnn.classes_.astype(str), np.asarray(train.class_names)[train.labels])
    fit_part, _ = cnn._split(labels)
    assert len(train) - 1 in fit_part  # the single sequence is trained on, never held out
    for proba in cnn.predict_proba_modalities(batch).values():
        assert np.isfinite(proba).all() and np.allclose(proba.sum(axis=1), 1.0)


# ---------------------------------------------------------------------- indistinguishable classes
@pytest.mark.parametrize(("kind", "reduce"), [("svm", "pca"), ("knn", "som")])
def test_identical_sequences_in_every_class_give_a_distribution(kind, reduce):
    batch = make_batch(n_per_class=4, probes=25, grid=(8, 8))
    batch.frames[:] = batch.frames[0]
    batch.normals[:] = batch.normals[0]
    model = ConventionalClassifier(kind=kind, reduce=reduce, **FAST_CONVENTIONAL)
    with np.errstate(invalid="ignore"):  # PCA's explained-variance ratio of constant features is 0 / 0
        model.fit(batch)
    raw = model.pipeline_.predict_proba(batch)  # the estimator's own output, before the base class checks
    assert np.isfinite(raw).all() and np.allclose(raw.sum(axis=1), 1.0) and (raw >= 0).all()
    assert (raw == raw[0]).all()  # the same input gives the same answer


@pytest.mark.parametrize("field", ["normals", "positions"])
def test_infinite_normals_and_positions_are_refused(one_of_a_class, field):
    batch, _, _, knn = one_of_a_class
    bad = batch.subset(np.arange(len(batch)))
    getattr(bad, field)[1, 2, 0] = np.inf
    with pytest.raises(DatasetError, match=f"{field} contain NaN or Inf"):
        knn.predict(bad)
    for model in (ConventionalClassifier(kind="knn"), CNNClassifier(**FAST_CNN)):
        with pytest.raises(DatasetError, match=f"{field} contain NaN or Inf"):
            model.fit(bad)
