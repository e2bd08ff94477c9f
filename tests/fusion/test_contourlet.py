"""Contourlet transform: perfect reconstruction, directional selectivity, the pyramid against scipy, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import pywt
from scipy.ndimage import convolve1d

from fusion.contourlet import (
    contourlet,
    dfb_windows,
    direction_angles,
    icontourlet,
    lp_analysis,
    lp_filters,
    subband_std,
)
from perception.errors import DatasetError

N = 32
YY, XX = np.mgrid[:N, :N]


def _grating_for(angle: float, r_min: float = 12.0, r_max: float = 15.5) -> tuple[int, int]:
    """Integer frequency (u, v) cycles per frame, in the finest band, closest in direction to ``angle``."""
    best = None
    for u in range(-16, 17):
        for v in range(17):
            if not r_min <= np.hypot(u, v) <= r_max:
                continue
            err = abs((np.arctan2(v, u) - angle + np.pi / 2) % np.pi - np.pi / 2)
            if best is None or err < best[0] - 1e-12:
                best = (err, u, v)
    assert best[0] < np.radians(1.0)  # the lattice has a point within a degree of every wedge centre
    return best[1], best[2]


def test_perfect_reconstruction_float64():
    rng = np.random.default_rng(1)
    frames = rng.standard_normal((3, 4, N, N))  # batch axes are kept
    coeffs = contourlet(frames)
    assert coeffs.lowpass.shape == (3, 4, 8, 8)
    assert [b.shape for b in coeffs.bands] == [(3, 4, 8, 16, 16), (3, 4, 16, N, N)]
    back = icontourlet(coeffs)
    assert np.linalg.norm(back - frames) / np.linalg.norm(frames) < 1e-10
    # Also for a smooth, realistic tactile-like image (a bump) and other level choices.
    bump = np.exp(-((XX - 13.0) ** 2 + (YY - 18.0) ** 2) / 40.0)
    for levels in [(0,), (2,), (1, 2), (3, 4)]:
        back = icontourlet(contourlet(bump, levels))
        assert np.linalg.norm(back - bump) / np.linalg.norm(bump) < 1e-10


def test_windows_are_a_tight_real_frame():
    for rows, cols, levels in [(32, 32, 4), (16, 16, 3), (16, 24, 2), (8, 8, 4)]:
        w = dfb_windows(rows, cols, levels)
        assert w.shape == (2**levels, rows, cols)
        np.testing.assert_allclose((w**2).sum(axis=0), 1.0, atol=1e-14)
        # Even (W(f) == W(-f)) so that every subband of a real image is real.
        np.testing.assert_allclose(w, np.roll(w[:, ::-1, ::-1], (1, 1), axis=(1, 2)), atol=1e-14)
        # Mirror-symmetric: flipping x (u -> -u) maps wedge k (angle k pi / K) to wedge K - k.
        mirrored = np.roll(w[:, :, ::-1], 1, axis=2)
        np.testing.assert_allclose(mirrored**2, w[(-np.arange(2**levels)) % 2**levels] ** 2, atol=1e-14)
    # Tight frame: the subbands carry exactly the band-pass image's energy.
    rng = np.random.default_rng(2)
    x = rng.standard_normal((N, N))
    _, band = lp_analysis(x)
    fine = contourlet(x).bands[-1]
    assert np.isclose((fine**2).sum(), (band**2).sum(), rtol=1e-12)


def test_pyramid_matches_scipy_periodic_convolution():
    """One LP level equals filtering with the 9/7 pair by scipy (wrap mode) and resampling by hand."""
    h, g = lp_filters()
    ref = pywt.Wavelet("bior4.4")
    assert np.isclose(h.sum(), np.sqrt(2)) and len(h) == 9 and len(g) == 7
    np.testing.assert_allclose(h, np.trim_zeros(np.asarray(ref.dec_lo)))
    rng = np.random.default_rng(3)
    x = rng.standard_normal((N, 24))
    coarse, band = lp_analysis(x)
    smooth = convolve1d(convolve1d(x, h, axis=0, mode="wrap"), h, axis=1, mode="wrap")
    np.testing.assert_allclose(coarse, smooth[::2, ::2], atol=1e-12)
    up = np.zeros_like(x)
    up[::2, ::2] = smooth[::2, ::2]
    predicted = convolve1d(convolve1d(up, g, axis=0, mode="wrap"), g, axis=1, mode="wrap")
    np.testing.assert_allclose(band, x - predicted, atol=1e-12)
    # The 9/7 pair reproduces constants: a flat image has no band-pass energy (to the ~1e-12 precision of
    # the published filter taps).
    _, flat_band = lp_analysis(np.full((N, N), 3.5))
    assert np.abs(flat_band).max() < 1e-10 * 3.5


@pytest.mark.parametrize("k", range(16))
def test_grating_lands_in_its_direction(k):
    angle = direction_angles(4)[k]
    u, v = _grating_for(angle)
    grating = np.cos(2 * np.pi * (u * XX + v * YY) / N)
    energy = (contourlet(grating).bands[-1] ** 2).sum(axis=(-2, -1))
    assert np.argmax(energy) == k
    assert energy[k] / energy.sum() > 0.9
    # Most of the grating's energy is in the finest band (it is a fine grating), hence in subband k.
    assert energy[k] > 0.5 * (grating**2).sum()


def test_subband_std_equals_direct_std():
    rng = np.random.default_rng(4)
    frames = rng.standard_normal((2, 3, N, N)).astype(np.float32)
    direct = contourlet(frames).bands[-1].std(axis=(-2, -1))
    fast = subband_std(frames, chunk=4)  # chunks smaller than the batch
    assert fast.shape == (2, 3, 16)
    np.testing.assert_allclose(fast, direct, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(subband_std(frames[0, 0, :16, :16], levels=3),
                               contourlet(frames[0, 0, :16, :16], (3,)).bands[-1].std(axis=(-2, -1)), rtol=1e-9)


@pytest.mark.parametrize("cores", [1, 3])
def test_subband_std_in_threads_equals_direct_std_and_the_one_thread_bits(monkeypatch, cores):
    """Chunks run on one thread per core: the same numbers as the direct std, and the same bits as one thread; with
    frames large enough that some chunks are rescaled (their squares would overflow) and others not."""
    import fusion.contourlet as module

    rng = np.random.default_rng(5)
    frames = rng.standard_normal((23, N, N))
    frames[9:13] *= 1e200  # chunks of 4: chunk 2 rescaled, chunk 3 in part
    direct = np.concatenate([contourlet(frames[:9]).bands[-1].std(axis=(-2, -1)),
                             1e200 * contourlet(frames[9:13] / 1e200).bands[-1].std(axis=(-2, -1)),
                             contourlet(frames[13:]).bands[-1].std(axis=(-2, -1))])
    monkeypatch.setattr(module, "usable_cores", lambda: 1)
    alone = subband_std(frames, chunk=4)
    monkeypatch.setattr(module, "usable_cores", lambda: cores)
    threaded = subband_std(frames, chunk=4)
    np.testing.assert_allclose(threaded, direct, rtol=1e-9)
    assert threaded.tobytes() == alone.tobytes()


def test_subband_std_in_threads_names_the_first_chunk_with_nan(monkeypatch):
    import fusion.contourlet as module

    monkeypatch.setattr(module, "usable_cores", lambda: 4)
    frames = np.zeros((20, N, N))
    frames[17, 3, 3] = np.nan
    frames[6, 0, 0] = np.inf
    with pytest.raises(DatasetError, match=r"frames 4\.\.7 contain NaN or Inf"):
        subband_std(frames, chunk=4)


def test_constant_and_spike_images_are_finite():
    flat = np.full((N, N), 7.0)
    coeffs = contourlet(flat)
    assert all(np.isfinite(b).all() for b in coeffs.bands)
    assert np.abs(coeffs.bands[-1]).max() < 1e-10 * 7.0
    assert np.abs(subband_std(flat)).max() < 1e-10 * 7.0
    spike = np.zeros((N, N))
    spike[4, 8] = 1.0  # on the decimation lattice, so the band-pass image is mirror-symmetric about it
    coeffs = contourlet(spike)
    assert all(np.isfinite(b).all() for b in coeffs.bands)
    np.testing.assert_allclose(icontourlet(coeffs), spike, atol=1e-12)
    std = subband_std(spike)
    assert np.isfinite(std).all() and (std > 0).all()
    # A point hits every direction: by symmetry, opposite-slope wedges (k and 16 - k) get equal energy.
    np.testing.assert_allclose(std[1:], std[1:][::-1], rtol=1e-9)


def test_bad_frames_raise():
    with pytest.raises(DatasetError, match="divisible by 4"):
        contourlet(np.zeros((30, 30)))
    with pytest.raises(DatasetError, match="NaN or Inf"):
        contourlet(np.full((N, N), np.nan))
    with pytest.raises(DatasetError, match="NaN or Inf"):
        subband_std(np.full((2, N, N), np.inf))
    with pytest.raises(DatasetError, match="rows, cols"):
        contourlet(np.zeros(5))
    with pytest.raises(DatasetError, match="divisible by 2"):
        subband_std(np.zeros((3, 15, 16)))
