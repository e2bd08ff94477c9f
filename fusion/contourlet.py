"""Contourlet transform (Do & Vetterli 2005): a Laplacian pyramid whose band-pass images are split by direction.

What we built, and why:

- **Laplacian pyramid (LP)**, decimated as in Do & Vetterli, with the biorthogonal CDF 9/7 pair (PyWavelets'
  ``bior4.4``: 9-tap analysis low-pass ``h``, 7-tap synthesis low-pass ``g``, both symmetric and centred) and
  periodic boundaries (tactile frames are small; periodic extension keeps every operator an exact matrix).
  One level: ``c = down2(h * x)`` and ``d = x - g * up2(c)``; the inverse ``x = d + g * up2(c)`` is exact
  whatever the filters, so the pyramid reconstructs perfectly. Because the filters are separable and the
  boundary periodic, each step is two small matrix products per frame (``A x A^T``), fast on a batch.
- **Directional filter bank (DFB)**: a frequency-domain directional partition instead of Bamberger-Smith
  quincunx fan filters with resampling (the construction of the non-subsampled and the frequency-domain
  contourlet variants). ``2**l`` wedge windows ``W_k`` tile the orientations of the frequency plane with
  smooth (Meyer-polynomial) transitions and ``sum_k W_k**2 == 1`` at every frequency, so the bank is a tight
  frame: analysis ``y_k = IFFT(W_k FFT(d))``, synthesis ``d = sum_k IFFT(W_k FFT(y_k))``, exact to rounding.
  It separates what an ``l``-level tree-structured DFB separates (``2**l`` wedges of orientation) but is not
  built as a tree of two-channel stages. Why: exact reconstruction without resampling lattices,
  wedges of equal angular width (the DFB's are equal in slope), windows that are real and even (real
  subbands), and subband energies computable from one FFT per frame (Parseval) -- what makes per-frame
  features for 570,000 frames take seconds. The subbands are not decimated (redundancy ``2**l`` per band).

Conventions: a frame is (rows, cols) = (y, x). Wedge ``k`` of ``K`` is centred on the *frequency* direction
``theta_k = k pi / K`` (radians from the column axis x towards the row axis y), so a grating
``cos(2 pi (u x + v y))`` with ``atan2(v, u) = theta_k`` lands in wedge ``k``; its stripes run at
``theta_k + pi / 2``. With ``levels=(3, 4)`` a 32 x 32 frame gives two pyramid levels: 8 directional subbands
of 16 x 16 and 16 of 32 x 32 (the finest), plus an 8 x 8 low-pass image.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache

import numpy as np
import pywt
from threadpoolctl import threadpool_limits

from perception.errors import DatasetError, InvalidArgumentError
from perception.runtime import usable_cores

#: DFB levels per pyramid level, coarse to fine (Do's toolbox ``nlevs``): 8 then 16 directions.
DEFAULT_LEVELS = (3, 4)
#: Half-width of the smooth transition between neighbouring wedges, in wedge widths (< 0.5).
TRANSITION = 0.25
#: Frames per chunk in :func:`subband_std` (bounds memory at about 30 MB per 1,000 frames of 32 x 32).
CHUNK = 4096


@dataclass(eq=False)
class Contourlet:
    """Contourlet coefficients of a batch of frames (leading batch shape ``B``).

    Attributes:
        lowpass: (*B, R / 2**J, C / 2**J) the coarsest low-pass image.
        bands: J arrays, coarse to fine; level ``j`` is (*B, 2**levels[j], R_j, C_j) directional subbands.
        levels: DFB levels per pyramid level, coarse to fine.
        shape: (R, C) of the transformed frames.
    """

    lowpass: np.ndarray
    bands: list[np.ndarray]
    levels: tuple[int, ...]
    shape: tuple[int, int]


# ----------------------------------------------------------------------------------------- filters
def _centred_taps(taps) -> np.ndarray:
    """Non-zero taps of a symmetric PyWavelets filter, centred (odd length)."""
    taps = np.trim_zeros(np.asarray(taps, dtype=np.float64))
    if len(taps) % 2 == 0 or not np.allclose(taps, taps[::-1]):
        raise AssertionError("LP filters must be symmetric with odd length")
    return taps


@cache
def lp_filters() -> tuple[np.ndarray, np.ndarray]:
    """(analysis low-pass h, synthesis low-pass g) of the pyramid: CDF 9/7 (``bior4.4``), each summing to sqrt 2."""
    wavelet = pywt.Wavelet("bior4.4")
    return _centred_taps(wavelet.dec_lo), _centred_taps(wavelet.rec_lo)


def _circulant(taps: np.ndarray, n: int) -> np.ndarray:
    """(n, n) matrix of periodic convolution with centred symmetric ``taps``."""
    m = np.zeros((n, n))
    half = len(taps) // 2
    rows = np.arange(n)
    for offset, value in zip(range(-half, half + 1), taps):
        np.add.at(m, (rows, (rows + offset) % n), value)  # add: a filter longer than n wraps onto itself
    return m


@cache
def lp_matrices(n: int) -> tuple[np.ndarray, np.ndarray]:
    """1-D pyramid operators for a periodic signal of even length ``n``.

    Returns ``(analysis, synthesis)``: ``analysis`` (n/2, n) = downsample(h *), ``synthesis`` (n, n/2) =
    g * upsample, so one 2-D level is ``c = A_r x A_c^T`` and the low-pass prediction ``S_r c S_c^T``.
    """
    h, g = lp_filters()
    analysis = _circulant(h, n)[::2]
    synthesis = _circulant(g, n)[:, ::2]  # upsampling puts c[m] at 2m: keep the even columns of g *
    analysis.setflags(write=False)
    synthesis.setflags(write=False)
    return analysis, synthesis


def _left(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``m @ x`` over the last two axes of a batch, as one large matrix product."""
    return np.swapaxes(np.swapaxes(x, -1, -2) @ m.T, -1, -2)


def lp_analysis(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pyramid level of (..., R, C) images (R, C even): (coarse (..., R/2, C/2), band-pass (..., R, C))."""
    a_r, s_r = lp_matrices(x.shape[-2])
    a_c, s_c = lp_matrices(x.shape[-1])
    coarse = _left(a_r, x @ a_c.T)
    return coarse, x - _left(s_r, coarse @ s_c.T)


def lp_synthesis(coarse: np.ndarray, band: np.ndarray) -> np.ndarray:
    """Inverse of :func:`lp_analysis`."""
    _, s_r = lp_matrices(band.shape[-2])
    _, s_c = lp_matrices(band.shape[-1])
    return band + _left(s_r, coarse @ s_c.T)


def _meyer_step(u: np.ndarray) -> np.ndarray:
    """Smooth 0 -> 1 step on [0, 1] with ``step(u) + step(1 - u) == 1`` (Meyer's polynomial, then sin^2)."""
    u = np.clip(u, 0.0, 1.0)
    nu = u**4 * (35 - 84 * u + 70 * u**2 - 20 * u**3)
    return np.sin(0.5 * np.pi * nu) ** 2


@cache
def dfb_windows(rows: int, cols: int, levels: int) -> np.ndarray:
    """(2**levels, rows, cols) real, even DFB windows on the FFT grid, ``sum_k W_k**2 == 1`` everywhere.

    Wedge ``k`` is centred on frequency direction ``k pi / K``; DC is shared equally (it has no direction).
    """
    k_dirs = 2**levels
    if k_dirs == 1:
        return np.ones((1, rows, cols))
    wedges = np.arange(k_dirs)[:, None, None]

    def squared(fy, fx):
        theta = np.mod(np.arctan2(fy[:, None], fx[None, :]), np.pi)  # a real image's spectrum is point-symmetric
        t = theta * k_dirs / np.pi + 0.5  # wedge coordinate: wedge k spans [k, k + 1)

        def share(b):  # fraction of the weight that boundary b hands to the wedge above it
            u = np.mod(t - b + k_dirs / 2, k_dirs) - k_dirs / 2  # periodic distance to the boundary
            return _meyer_step((u + TRANSITION) / (2 * TRANSITION))

        return share(wedges) * (1.0 - share(wedges + 1))

    # The Nyquist row / column of an even grid is both +1/2 and -1/2 cycle per sample: average the two readings,
    # which keeps every window even (real subbands) and mirror-symmetric (a mirrored image swaps wedges exactly).
    def readings(n):
        f = np.fft.fftfreq(n)
        flipped = f.copy()
        flipped[n // 2] *= -1 if n % 2 == 0 else 1  # fftfreq says -1/2; +1/2 is the same bin
        return f, flipped

    w2 = np.mean([squared(fy, fx) for fy in readings(rows) for fx in readings(cols)], axis=0)
    w2[:, 0, 0] = 1.0 / k_dirs  # DC has no direction: share it equally
    w2 /= w2.sum(axis=0, keepdims=True)  # exact partition of unity (a no-op up to rounding)
    w = np.sqrt(w2)
    w.setflags(write=False)
    return w


def direction_angles(levels: int) -> np.ndarray:
    """(2**levels,) frequency direction of each wedge's centre, radians in [0, pi)."""
    return np.arange(2**levels) * np.pi / 2**levels


# --------------------------------------------------------------------------------------- transform
def _check_frames(frames, levels: tuple[int, ...], check_values: bool = True) -> np.ndarray:
    x = np.asarray(frames)
    if x.ndim < 2 or x.shape[-1] == 0 or x.shape[-2] == 0:
        raise DatasetError(f"contourlet: expected (..., rows, cols) frames, got shape {x.shape}")
    if any(lv < 0 for lv in levels):
        raise InvalidArgumentError(f"contourlet: DFB levels must be >= 0, got {levels}")
    step = 2 ** len(levels)
    if x.shape[-2] % step or x.shape[-1] % step:
        raise DatasetError(
            f"contourlet: {len(levels)} pyramid levels need rows and cols divisible by {step}, "
            f"got {x.shape[-2]} x {x.shape[-1]}"
        )
    if not np.issubdtype(x.dtype, np.number) or np.iscomplexobj(x):
        raise DatasetError(f"contourlet: frames must be real numbers, got dtype {x.dtype}")
    if check_values and not np.isfinite(x).all():
        raise DatasetError("contourlet: frames must be finite (NaN or Inf found)")
    return x


def contourlet(frames, levels: tuple[int, ...] = DEFAULT_LEVELS) -> Contourlet:
    """Contourlet transform of (..., R, C) frames, float64; ``levels``: DFB levels per pyramid level, coarse to fine.

    Raises:
        DatasetError: fewer than 2 dimensions, sizes not divisible by ``2**len(levels)``, NaN/Inf.
    """
    levels = tuple(int(lv) for lv in levels)
    x = _check_frames(frames, levels).astype(np.float64, copy=False)
    shape = x.shape[-2:]
    # The transform is linear: frames beyond 2**256 in magnitude (or all below 2**-256) go through it scaled by a
    # power of two (exact), so that its FFTs cannot overflow (Inf from 1e307 on) or underflow.
    exponent = rescale_exponent(np.abs(x).max(initial=0.0))
    x = np.ldexp(x, -exponent) if exponent else x
    bands = []
    for lv in reversed(levels):  # fine to coarse
        x, band = lp_analysis(x)
        w = dfb_windows(band.shape[-2], band.shape[-1], lv)
        spectrum = np.fft.fft2(band)[..., None, :, :]
        bands.append(np.fft.ifft2(spectrum * w).real)
    if exponent:
        with np.errstate(over="ignore"):  # overflow is caught just below
            x, bands = np.ldexp(x, exponent), [np.ldexp(b, exponent) for b in bands]
        if not (np.isfinite(x).all() and all(np.isfinite(b).all() for b in bands)):
            raise DatasetError("contourlet: the coefficients of frames this large exceed float64; rescale the frames")
    return Contourlet(lowpass=x, bands=bands[::-1], levels=levels, shape=shape)


def rescale_exponent(peak):
    """The power of two to divide by that brings magnitudes ``peak`` into [0.5, 1); 0 (leave alone) where they lie
    within [2**-256, 2**256] (squares, cubes and FFT sums stay far from overflow and underflow) or are 0, so that
    ordinary data keeps its exact bytes."""
    exponent = np.frexp(peak)[1]
    return np.where(np.abs(exponent) > 256, exponent, 0)


def icontourlet(coeffs: Contourlet) -> np.ndarray:
    """Inverse of :func:`contourlet`: the (..., R, C) frames, float64."""
    x = np.asarray(coeffs.lowpass, dtype=np.float64)
    for lv, sub in zip(coeffs.levels, coeffs.bands):
        w = dfb_windows(sub.shape[-2], sub.shape[-1], lv)
        band = np.fft.ifft2((np.fft.fft2(sub) * w).sum(axis=-3)).real
        x = lp_synthesis(x, band)
    return x


# -------------------------------------------------------------------------------------- features
@cache
def _energy_matrix(rows: int, cols: int, levels: int) -> np.ndarray:
    """(rows * (cols // 2 + 1), K) weights turning |rfft2|^2 of a band into mean squares of its subbands."""
    w2 = dfb_windows(rows, cols, levels) ** 2
    half = w2[:, :, : cols // 2 + 1].copy()
    # rfft2 keeps columns 0..cols/2; the others are mirror images (the windows are even): count them twice.
    weight = np.full(cols // 2 + 1, 2.0)
    weight[0] = 1.0
    if cols % 2 == 0:
        weight[-1] = 1.0
    half *= weight / float(rows * cols) ** 2  # Parseval: sum |y|^2 = sum |Y|^2 / N, mean = / N again
    return half.reshape(len(w2), -1).T.copy()


def subband_std(frames, levels: int = 4, chunk: int = CHUNK) -> np.ndarray:
    """(..., 2**levels) standard deviation of each finest-scale directional subband of each (R, C) frame.

    The same numbers as ``contourlet(frames).bands[-1].std(axis=(-2, -1))`` (the finest band-pass image does
    not depend on coarser pyramid levels), computed from one FFT per frame by Parseval, in chunks.
    Units: those of the frames (mm for gap images).

    Raises:
        DatasetError: odd rows or cols, fewer than 2 dimensions, NaN/Inf.
    """
    x = _check_frames(frames, (levels,), check_values=False)  # checked chunk by chunk: no full-size copies
    lead, (rows, cols) = x.shape[:-2], x.shape[-2:]
    x = x.reshape(-1, rows, cols)
    k_dirs = 2**levels
    energy = _energy_matrix(rows, cols, levels)
    dc_gain = dfb_windows(rows, cols, levels)[:, 0, 0]
    out = np.empty((len(x), k_dirs))
    exponents = np.zeros(len(x), dtype=np.int64)

    def one_chunk(start: int) -> None:
        block = x[start : start + chunk].astype(np.float64)
        peak = np.abs(block).max(axis=(1, 2))
        if not np.isfinite(peak).all():
            raise DatasetError(f"subband_std: frames {start}..{start + len(block) - 1} contain NaN or Inf")
        # Energies square the readings: frames beyond 2**256 (or below 2**-256) are scaled by a power of two
        # (exact) so the squares neither overflow (NaN from 1e154 on) nor underflow; the std scales back below.
        exponent = rescale_exponent(peak)
        if exponent.any():
            block = np.ldexp(block, -exponent[:, None, None])
            exponents[start : start + chunk] = exponent
        _, band = lp_analysis(block)
        spectrum = np.fft.rfft2(band)
        power = (spectrum.real**2 + spectrum.imag**2).reshape(len(band), -1)
        mean = spectrum[:, 0, 0].real[:, None] * dc_gain / (rows * cols)
        out[start : start + chunk] = power @ energy - mean**2

    starts = range(0, len(x), chunk)
    workers = min(usable_cores(), len(starts))
    if workers > 1:
        # The FFTs and products release the GIL: one thread per core, each with one BLAS thread (18,240 SHREC
        # sequences of 25 frames on 2 cores: 9.4 -> 4.5 s; the same bits, each chunk computed alone either way).
        with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(workers) as pool:
            for _ in pool.map(one_chunk, starts):  # in order: the first chunk with NaN / Inf raises, as in a loop
                pass
    else:
        for start in starts:
            one_chunk(start)
    std = np.sqrt(np.maximum(out, 0.0))  # rounding can dip a zero variance below 0
    if exponents.any():
        with np.errstate(over="ignore"):  # overflow is caught just below
            std = np.ldexp(std, exponents[:, None])
        if not np.isfinite(std).all():
            raise DatasetError("subband_std: the subband std of frames this large exceeds float64; rescale the frames")
    return std.reshape(*lead, k_dirs)


__all__ = [
    "DEFAULT_LEVELS",
    "Contourlet",
    "contourlet",
    "dfb_windows",
    "direction_angles",
    "icontourlet",
    "lp_analysis",
    "lp_filters",
    "lp_matrices",
    "lp_synthesis",
    "rescale_exponent",
    "subband_std",
]
