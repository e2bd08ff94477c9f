"""Calibration: temperature scaling recovers a planted temperature, the tempered log rule's dependence is 0 for
independent touches and 1 for copies of one touch, ECE and reliability bins match hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import softmax

from fusion.calibration import (
    apply_calibration,
    apply_confidence_map,
    apply_temperature,
    ece_interval,
    ece_noise_floor,
    expected_calibration_error,
    fit_calibration,
    fit_confidence_map,
    fit_dependence,
    fit_temperature,
    fuse_tempered,
    negative_log_likelihood,
    reliability,
    tempered_exponent,
)
from fusion.decide import fuse_touches
from perception.errors import DatasetError, InvalidArgumentError


def _planted(temperature: float, n: int = 6000, c: int = 5, seed: int = 0):
    """Logits and labels drawn from softmax(logits / temperature)."""
    rng = np.random.default_rng(seed)
    z = rng.normal(0, 3.0, size=(n, c))
    p = softmax(z / temperature, axis=1)
    y = (p.cumsum(axis=1) > rng.random((n, 1))).argmax(axis=1)
    return z, y


def _gaussian_touches(n: int, k: int, copies: bool, seed: int = 0):
    """(n, k, 3) exact posteriors of touches x ~ N(mu_y, I) in 2-D (three classes, equal priors): independent
    draws, or k copies of one draw."""
    rng = np.random.default_rng(seed)
    means = np.array([[0.0, 0.0], [1.5, 0.0], [0.0, 1.5]])
    y = rng.integers(0, 3, n)
    x = means[y][:, None, :] + rng.normal(size=(n, 1 if copies else k, 2))
    x = np.repeat(x, k, axis=1) if copies else x
    logits = -0.5 * ((x[:, :, None, :] - means[None, None]) ** 2).sum(-1)
    return softmax(logits, axis=-1), y


class TestTemperature:
    @pytest.mark.parametrize("planted", [0.5, 1.0, 3.0])
    def test_recovers_planted_temperature(self, planted):
        z, y = _planted(planted)
        assert fit_temperature(z, y) == pytest.approx(planted, rel=0.08)

    def test_lowers_the_likelihood_loss(self):
        z, y = _planted(2.5)
        raw = softmax(z, axis=1)
        fitted = apply_temperature(raw, fit_temperature(np.log(raw), y))
        assert negative_log_likelihood(fitted, y) < negative_log_likelihood(raw, y)

    def test_apply_temperature_one_is_identity_and_keeps_the_order(self):
        p = np.array([[0.7, 0.2, 0.1], [0.0, 0.5, 0.5]])
        assert np.allclose(apply_temperature(p, 1.0), p, atol=1e-11)
        soft = apply_temperature(p, 4.0)
        assert np.allclose(soft.sum(axis=1), 1.0) and np.isfinite(soft).all()
        assert (soft.argmax(axis=1) == p.argmax(axis=1)).all() and soft[0, 0] < 0.7

    @pytest.mark.parametrize("bad", [0.0, -1.0, np.inf, np.nan, True])
    def test_refuses_bad_temperatures(self, bad):
        with pytest.raises(InvalidArgumentError, match="temperature"):
            apply_temperature(np.array([[0.5, 0.5]]), bad)

    def test_refuses_non_finite_logits(self):
        with pytest.raises(DatasetError, match="fit_temperature"):
            fit_temperature(np.array([[0.0, np.nan], [1.0, 0.0]]), np.array([0, 1]))


class TestSmoothing:
    def test_recovers_planted_temperature_and_uniform_share(self):
        rng = np.random.default_rng(3)
        z = rng.normal(0, 3.0, size=(8000, 4))
        p = 0.8 * softmax(z / 0.5, axis=1) + 0.2 / 4
        y = (p.cumsum(axis=1) > rng.random((len(z), 1))).argmax(axis=1)
        t, eps = fit_calibration(z, y)
        assert t == pytest.approx(0.5, rel=0.1) and eps == pytest.approx(0.2, abs=0.03)
        assert np.allclose(apply_calibration(softmax(z, axis=1), 1.0, 0.0), softmax(z, axis=1), atol=1e-11)

    @pytest.mark.parametrize("fit", [fit_temperature, fit_calibration])
    @pytest.mark.parametrize("bounds", [(2.0, 1.0), (0.0, 1.0), (0.5, np.inf)])
    def test_both_fits_refuse_bad_bounds_naming_themselves(self, fit, bounds):
        z, y = np.array([[0.0, 1.0], [1.0, 0.0]]), np.array([0, 1])
        with pytest.raises(InvalidArgumentError, match=f"{fit.__name__}: bounds"):
            fit(z, y, bounds=bounds)

    @pytest.mark.parametrize("fit", [fit_temperature, fit_calibration])
    def test_both_fits_refuse_a_single_sample_naming_themselves(self, fit):
        with pytest.raises(DatasetError, match=f"{fit.__name__}: expected finite"):
            fit(np.array([[0.0, 1.0]]), np.array([1]))

    @pytest.mark.parametrize("fit", [fit_temperature, fit_calibration])
    @pytest.mark.parametrize("y", [[0, 2], [0, -1], [0], [0, 1, 1], [0.0, 1.0], [[0], [1]]])
    def test_both_fits_refuse_labels_that_are_not_class_indices_naming_themselves(self, fit, y):
        """Labels out of 0..C-1 (a negative index would silently pick the last class), of another count or
        shape, or not integers are refused before any fitting."""
        z = np.array([[0.0, 1.0], [1.0, 0.0]])
        with pytest.raises(DatasetError, match=f"{fit.__name__}: expected 2 class indices"):
            fit(z, np.array(y))


    def test_refuses_smoothing_of_one(self):
        with pytest.raises(InvalidArgumentError, match="smoothing"):
            apply_calibration(np.array([[0.5, 0.5]]), 1.0, 1.0)


class TestConfidenceMap:
    def test_overconfident_decisions_mapped_to_their_share_right(self):
        rng = np.random.default_rng(4)
        y = rng.integers(0, 3, 5000)
        decision = np.where(rng.random(5000) < 0.6, y, (y + 1) % 3)  # 60 % right, always 90 % sure
        proba = np.full((5000, 3), 0.05)
        proba[np.arange(5000), decision] = 0.9
        knots, values = fit_confidence_map(proba, y)
        mapped = apply_confidence_map(proba, knots, values)
        assert mapped.max(axis=1) == pytest.approx(np.full(5000, 0.6), abs=0.02)
        assert (mapped.argmax(axis=1) == decision).all() and np.allclose(mapped.sum(axis=1), 1.0)
        assert expected_calibration_error(mapped, y) < 0.02
        assert expected_calibration_error(proba, y) > 0.25

    def test_never_changes_the_decision(self):
        p = np.array([[0.5, 0.45, 0.05], [0.2, 0.7, 0.1], [1.0, 0.0, 0.0]])
        mapped = apply_confidence_map(p, np.array([0.0, 1.0]), np.array([0.1, 0.2]))
        assert (mapped.argmax(axis=1) == p.argmax(axis=1)).all() and np.isfinite(mapped).all()
        assert np.allclose(mapped.sum(axis=1), 1.0)


class TestTemperedRule:
    def test_zero_dependence_is_the_log_rule_and_one_the_geometric_mean(self):
        p = np.random.default_rng(1).dirichlet(np.ones(4), size=(6, 3))
        assert np.allclose(fuse_tempered(p, 0.0), fuse_touches(p, "log"))
        geometric = np.exp(np.log(p).mean(axis=1))
        assert np.allclose(fuse_tempered(p, 1.0), geometric / geometric.sum(axis=1, keepdims=True))
        assert np.allclose(fuse_touches(p, "tempered", dependence=0.3), fuse_tempered(p, 0.3))

    def test_copies_of_one_touch_with_full_dependence_give_that_touch(self):
        p = np.array([0.6, 0.3, 0.1])
        assert np.allclose(fuse_tempered(np.tile(p, (8, 1)), 1.0), p)

    def test_exponent(self):
        assert tempered_exponent(1, 0.7) == 1.0
        assert tempered_exponent(8, 0.5) == pytest.approx(1 / 4.5)
        with pytest.raises(InvalidArgumentError, match="dependence"):
            tempered_exponent(2, 1.5)

    def test_independent_touches_fit_no_dependence(self):
        sets = [_gaussian_touches(3000, k, copies=False, seed=k) for k in (2, 4, 8)]
        assert fit_dependence([s[0] for s in sets], [s[1] for s in sets]) < 0.05

    def test_copies_of_one_touch_fit_full_dependence(self):
        sets = [_gaussian_touches(3000, k, copies=True, seed=k) for k in (2, 4, 8)]
        assert fit_dependence([s[0] for s in sets], [s[1] for s in sets]) > 0.95

    def test_needs_groups_of_two(self):
        p, y = _gaussian_touches(10, 1, copies=False)
        with pytest.raises(DatasetError, match="K >= 2"):
            fit_dependence([p], [y])


class TestReliability:
    def test_hand_computed_ece(self):
        proba = np.array([[0.9, 0.1], [0.6, 0.4], [0.8, 0.2], [0.3, 0.7]])
        y = np.array([0, 1, 0, 1])
        # one decision per bin: |1 - 0.9|, |0 - 0.6|, |1 - 0.8|, |1 - 0.7| -> mean 0.3
        assert expected_calibration_error(proba, y, bins=10) == pytest.approx(0.3)
        # two bins: all four in (0.5, 1], 3 of 4 right at mean confidence 0.75 -> 0
        rel = reliability(proba, y, bins=2)
        assert rel["ece"] == pytest.approx(0.0) and list(rel["count"]) == [0, 4]
        assert rel["accuracy"][1] == pytest.approx(0.75) and rel["confidence"][1] == pytest.approx(0.75)

    def test_calibrated_by_construction_has_small_ece(self):
        z, y = _planted(1.0, n=20000)
        assert expected_calibration_error(softmax(z, axis=1), y) < 0.02
        assert expected_calibration_error(softmax(3 * z, axis=1), y) > 0.1  # overconfident

    def test_interval_over_groups_contains_the_value(self):
        z, y = _planted(1.0, n=2000)
        e = ece_interval(softmax(z, axis=1), y, np.arange(2000) // 20, n_boot=200)
        assert e["low"] <= e["ece"] <= e["high"] and e["n_groups"] == 100

    def test_noise_floor_of_a_calibrated_predictor(self):
        rng = np.random.default_rng(5)
        confidence = rng.uniform(0.4, 1.0, 300)
        floor = ece_noise_floor(confidence)
        assert 0.02 < floor < 0.12  # 300 decisions cannot show an ECE of 0
        assert ece_noise_floor(np.tile(confidence, 30)) < floor / 3

    def test_refuses_bad_labels(self):
        with pytest.raises(DatasetError, match="class indices"):
            reliability(np.array([[0.5, 0.5]]), np.array([2]))
