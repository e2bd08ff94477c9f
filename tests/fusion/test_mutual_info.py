"""fusion.mutual_info: scikit-learn's mutual-information estimate computed by sorting, compared with scikit-learn's
own output bit for bit, and with known answers where the estimator has one."""

import numpy as np
import pytest
from scipy.special import digamma
from sklearn.feature_selection import mutual_info_classif
from sklearn.neighbors import KDTree, NearestNeighbors

from fusion.mutual_info import _count_within, _kth_neighbour_distance, mutual_info_continuous


def _dataset(rng, kind):
    n, n_features, n_classes = int(rng.integers(4, 300)), int(rng.integers(1, 5)), int(rng.integers(1, 6))
    y = rng.integers(0, n_classes, n)
    if kind == "normal":
        X = rng.normal(size=(n, n_features))
    elif kind == "ties":  # a few distinct values: the jitter alone separates them
        X = rng.integers(0, 4, size=(n, n_features)).astype(float)
    elif kind == "scales":  # columns from 1e-8 to 1e8
        X = rng.normal(size=(n, n_features)) * 10.0 ** rng.integers(-8, 9, size=n_features)
    else:  # rounded, class-dependent: real information and near-ties
        X = np.round(rng.normal(size=(n, n_features)), 2) + 0.3 * y[:, None]
    return X, y


@pytest.mark.parametrize("kind", ["normal", "ties", "scales", "informative"])
def test_equals_scikit_learn_bit_for_bit(kind):
    rng = np.random.default_rng(["normal", "ties", "scales", "informative"].index(kind))
    compared = 0
    for trial in range(60):
        X, y = _dataset(rng, kind)
        if np.unique(y, return_counts=True)[1].max() < 2:
            continue
        k = int(rng.integers(1, 6))  # classes of 2..2k+1 samples take scikit-learn's brute-force path
        expected = mutual_info_classif(X, y, n_neighbors=k, random_state=trial)
        np.testing.assert_array_equal(mutual_info_continuous(X, y, n_neighbors=k, random_state=trial), expected)
        compared += 1
    assert compared > 40


def test_labels_of_any_kind_and_single_sample_classes():
    rng = np.random.default_rng(7)
    X = rng.normal(size=(80, 3))
    y = np.array(["mug", "cup", "bottle"] * 26 + ["lonely", "alone"], dtype=object)  # two single-sample classes
    X[:, 0] += (y == "mug") * 2.0
    expected = mutual_info_classif(X, y, random_state=3)
    got = mutual_info_continuous(X, y, random_state=3)
    np.testing.assert_array_equal(got, expected)
    assert got[0] > 0.3 > got[1]


def test_known_answers():
    """Two classes far apart: the estimate is digamma(N) - digamma(N / 2) (every radius holds only the sample's own
    class), about log 2; a feature independent of the class estimates near 0 and is clipped at 0 from below."""
    rng = np.random.default_rng(1)
    n = 2000
    y = np.repeat([0, 1], n // 2)
    separated = rng.normal(size=n) + 100.0 * y
    noise = rng.normal(size=n)
    gain = mutual_info_continuous(np.stack([separated, noise], axis=1), y, n_neighbors=3, random_state=0)
    assert gain[0] == pytest.approx(digamma(n) - digamma(n // 2), abs=1e-12)
    assert gain[0] == pytest.approx(np.log(2), abs=1e-3)
    assert 0.0 <= gain[1] < 0.01


def test_neighbour_distances_and_counts_equal_scikit_learns_trees():
    """On a 0.1 mm grid (distances such as 0.30000000000000004) the radii sit one float below a neighbour's
    distance and squaring rounds: the counts must still be the tree's."""
    rng = np.random.default_rng(2)
    for x in (np.arange(60) * 0.1, rng.permutation(np.arange(500) * 0.1), rng.normal(size=300),
              np.repeat(rng.normal(size=40), 3)):
        for k in (1, 3, 5):
            tree = NearestNeighbors(n_neighbors=k).fit(x[:, None])
            assert tree._fit_method == "kd_tree"
            expected = tree.kneighbors()[0][:, -1]
            np.testing.assert_array_equal(_kth_neighbour_distance(x, k), expected)
            radius = np.nextafter(expected, 0)
            counts = KDTree(x[:, None]).query_radius(x[:, None], radius, count_only=True)
            np.testing.assert_array_equal(_count_within(x, radius), counts)
    x = np.arange(100) * 0.1
    for radius in (np.full(100, 0.3), np.full(100, 0.30000000000000004), rng.uniform(0, 2, 100), np.zeros(100)):
        np.testing.assert_array_equal(_count_within(x, radius),
                                      KDTree(x[:, None]).query_radius(x[:, None], radius, count_only=True))


def test_refuses_what_scikit_learn_refuses():
    X = np.zeros((10, 2))
    with pytest.raises(ValueError, match="continuous"):
        mutual_info_continuous(X, np.linspace(0, 1, 10))
    for bad in (0, 2.5, 3.0):
        with pytest.raises(ValueError, match="n_neighbors"):
            mutual_info_continuous(X, np.arange(10) % 2, n_neighbors=bad)
        with pytest.raises(ValueError):  # scikit-learn refuses the same
            mutual_info_classif(X, np.arange(10) % 2, n_neighbors=bad)
    with pytest.raises(ValueError, match="n_neighbors"):  # scikit-learn reads True as 1; a flag is no count here
        mutual_info_continuous(X, np.arange(10) % 2, n_neighbors=True)
    with pytest.raises(ValueError, match="single sample"):
        mutual_info_continuous(X, np.arange(10))
    with pytest.raises(ValueError, match="NaN|infinity"):
        mutual_info_continuous(np.full((10, 2), np.nan), np.arange(10) % 2)


def test_benchmark_reports_equal_floats_and_fails_when_they_differ(capsys, monkeypatch):
    from benchmarks import information_gain as bench

    assert bench.main(["--sequences", "120", "--repeats", "1", "--json"]) == 0
    out = capsys.readouterr().out
    assert "| synthetic | 120 x 285 |" in out and "| yes |" in out and '"equal": true' in out
    import fusion.mutual_info as mi

    real = mi.mutual_info_continuous
    monkeypatch.setattr(mi, "mutual_info_continuous", lambda *a, **k: real(*a, **k) + 1e-12)
    assert bench.main(["--sequences", "120", "--repeats", "1"]) == 1
    assert "| NO |" in capsys.readouterr().out


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning", "ignore:invalid value:RuntimeWarning")
def test_a_column_scaled_to_nan_is_refused_as_scikit_learn_refuses_it():
    """+-1e308 alternating: the column's variance overflows and scaling makes it NaN."""
    X = np.array([1e308, -1e308] * 8)[:, None]
    y = np.arange(16) % 2
    with pytest.raises(ValueError, match="NaN"):
        mutual_info_classif(X, y, random_state=0)
    with pytest.raises(ValueError, match="NaN"):
        mutual_info_continuous(X, y, random_state=0)
    with pytest.raises(ValueError, match="NaN"):  # beside a sound column too
        mutual_info_continuous(np.hstack([X, np.arange(16.0)[:, None]]), y, random_state=0)


def test_sparse_X_is_refused_with_a_value_error_as_scikit_learn_refuses_it():
    import scipy.sparse

    X, y = scipy.sparse.csr_matrix(np.eye(6)), np.arange(6) % 2
    with pytest.raises(ValueError):
        mutual_info_classif(X, y, discrete_features=False)
    with pytest.raises(ValueError, match="dense"):
        mutual_info_continuous(X, y)


def test_the_callers_array_is_not_modified():
    X = np.random.default_rng(0).normal(size=(30, 2))
    before = X.copy()
    mutual_info_continuous(X, np.arange(30) % 3, random_state=0)
    np.testing.assert_array_equal(X, before)


def test_benchmark_ratio_is_scikit_learns_time_over_ours(monkeypatch):
    from benchmarks import information_gain as bench

    times = iter([0.5, 2.0])  # ours first, then scikit-learn's
    monkeypatch.setattr(bench, "median_time", lambda fn, repeats: (next(times), fn()))
    X, y = bench.synthetic_features(60, 0)
    row = bench.compare(X, y, 1, 0)
    assert (row["ours_s"], row["sklearn_s"], row["ratio"]) == (0.5, 2.0, 4.0)
