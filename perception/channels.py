"""Image channels of the multi-view attention model, computed on a stack of rendered views at once.

Every channel works on (N, H, W) stacks (N views) with filters that act only within each view
(``sigma = (0, s, s)``), so all views cost one filter call. Background pixels never count: smoothing is
normalised convolution over the object mask, and filters that need a full image see the background
filled with the nearby object intensity (so the silhouette against an empty background is not mistaken for
texture; the ``edges`` channel is where silhouettes count, as depth discontinuities).

Channels (scales in pixels; one pixel is ``camera.pixel_mm`` mm, about 1.2 mm at the defaults):

- ``intensity``: centre-surround |G(1) - G(4)| of the headlight shading (Itti et al. 1998).
- ``contrast``: local standard deviation of the shading in a Gaussian window (sigma 2).
- ``orientation``: energy of complex Gabor filters (wavelength 6, sigma 3) at 0, 45, 90 and 135 degrees,
  each normalised, then summed.
- ``curvature``: RMS curvature of the surface from the normal map, sqrt((|dn/dx|^2 + |dn/dy|^2) / 2), in
  1/mm, zero across depth discontinuities.
- ``edges``: depth discontinuities (a jump of more than 4 pixels between neighbours, silhouettes included)
  plus normal creases (1 - cos of the angle between neighbouring normals).
- ``entropy``: Shannon entropy of the shading quantised to 16 levels in a Gaussian window (sigma 2), in [0, 1].
- ``symmetry``: the generalised symmetry transform of Reisfeld, Wolfson & Yeshurun (1995): pairs of gradient
  pixels at distances 4, 8, 12 placed symmetrically about the pixel vote with their log-magnitudes times
  the phase weight (1 - cos(t1 + t2 - 2 a))(1 - cos(t1 - t2)), weighted by exp(-distance / 8).
- ``color_opponency`` (coloured meshes only): centre-surround of R - G and B - (R + G) / 2.
- ``dkl`` (coloured meshes only): centre-surround of the two chromatic axes of DKL space, L - M and
  S - (L + M), from RGB through the LMS matrix of Reinhard et al. (2001).

Each channel becomes a conspicuity map with :func:`itti_normalize`.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage

from perception.errors import InvalidArgumentError
from perception.runtime import usable_cores

#: Channels computed for every mesh, in order.
GEOMETRY_CHANNELS = ("intensity", "contrast", "orientation", "curvature", "edges", "entropy", "symmetry")
#: Channels computed only when the mesh has vertex colours.
COLOR_CHANNELS = ("color_opponency", "dkl")
ALL_CHANNELS = GEOMETRY_CHANNELS + COLOR_CHANNELS

_EPS = 1e-9
_RGB_TO_LMS = np.array([[0.3811, 0.5783, 0.0402], [0.1967, 0.7244, 0.0782], [0.0241, 0.1288, 0.8444]])


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    return ndimage.gaussian_filter(x, sigma=(0, sigma, sigma), mode="constant")


def _radius(sigma: float) -> int:
    """Half-width (pixels) of :func:`_blur`'s kernel (scipy's default ``truncate=4``)."""
    return int(4.0 * sigma + 0.5)


def _window(mask: np.ndarray, margin: int) -> tuple[slice, slice, slice]:
    """The rows and columns, over all views, that hold object pixels, widened by ``margin`` (within the image)."""
    rows, cols = np.flatnonzero(mask.any(axis=(0, 2))), np.flatnonzero(mask.any(axis=(0, 1)))
    if not len(rows):
        return slice(None), slice(0, 0), slice(0, 0)
    height, width = mask.shape[1:]
    return (
        slice(None),
        slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, height)),
        slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, width)),
    )


def _blur_object(x: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``_blur(x, sigma)`` of an ``x`` that is zero off the object, filtering only the object's rows and columns
    widened by the kernel's reach: outside them the blur is zero, inside them the same values."""
    out = np.zeros(x.shape)
    window = _window(mask, _radius(sigma))
    out[window] = _blur(x[window], sigma)
    return out


def masked_blur(x: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of ``x`` over the object pixels only (normalised convolution); 0 on the background."""
    return _MaskBlur(mask)(x, sigma)


class _MaskBlur:
    """:func:`masked_blur` for one mask, blurring the mask once per sigma (the same values, fewer filter calls).
    ``value`` passes ``_blur(x * mask, sigma)`` when the caller has it already."""

    def __init__(self, mask: np.ndarray):
        self.mask = mask
        self._weights: dict[float, np.ndarray] = {}

    def weight(self, sigma: float) -> np.ndarray:
        if sigma not in self._weights:
            self._weights[sigma] = _blur_object(self.mask.astype(np.float64), self.mask, sigma)
        return self._weights[sigma]

    def value(self, x: np.ndarray, sigma: float) -> np.ndarray:
        """``_blur(x * mask, sigma)``."""
        return _blur_object(x * self.mask, self.mask, sigma)

    def __call__(self, x: np.ndarray, sigma: float, value: np.ndarray | None = None) -> np.ndarray:
        weight = self.weight(sigma)
        value = self.value(x, sigma) if value is None else value
        return np.divide(value, weight, out=np.zeros_like(value), where=weight > 1e-3) * self.mask


def fill_background(
    x: np.ndarray, mask: np.ndarray, sigma: float = 4.0, *, _blurs: _MaskBlur | None = None,
    _value: np.ndarray | None = None,
) -> np.ndarray:
    """Copy of ``x`` whose background pixels hold the nearby object value (else the view's object mean).
    (``_blurs`` and ``_value``, ``_blur(x * mask, sigma)``, let :func:`compute_channels` share filter calls.)"""
    blurs = _blurs or _MaskBlur(mask)
    weight = blurs.weight(sigma)
    value = blurs.value(x, sigma) if _value is None else _value
    near = np.divide(value, weight, out=np.zeros_like(x), where=weight > 1e-3)
    counts = mask.sum(axis=(1, 2), keepdims=True)
    mean = np.divide(
        (x * mask).sum(axis=(1, 2), keepdims=True), counts, out=np.zeros(counts.shape), where=counts > 0
    )
    far = np.where(weight > 1e-3, near, mean)
    return np.where(mask, x, far)


def itti_normalize(maps: np.ndarray, mask: np.ndarray | None = None, window: int = 7) -> np.ndarray:
    """Itti's map normalisation N(.) over a whole stack: scale to [0, 1] by the global maximum, then
    multiply by (1 - m)^2, m = mean of the other local maxima, promoting maps with few strong peaks.

    Local maxima are pixels equal to the maximum in a ``window`` x ``window`` neighbourhood and above 5 % of the
    global maximum (so that flat zero regions are not counted). Returns float64 in [0, 1]; all zero when the
    input is.
    """
    if mask is not None:
        # Zero off the object: work within the object's rows and columns widened by the neighbourhood (the
        # same maximum, the same peaks, zero elsewhere).
        out = np.zeros(np.broadcast_shapes(np.shape(maps), mask.shape))
        region = _window(mask, window // 2) if mask.ndim == 3 and np.ndim(maps) == 3 else (Ellipsis,)
        out[region] = itti_normalize(np.where(mask[region], maps[region], 0.0), None, window)
        return out
    maps = np.asarray(maps, dtype=np.float64)
    top = float(maps.max()) if maps.size else 0.0
    if not np.isfinite(top) or top <= _EPS:
        return np.zeros(maps.shape)
    x = np.clip(maps / top, 0.0, 1.0)
    peaks = (x == ndimage.maximum_filter(x, size=(1, window, window))) & (x > 0.05)
    values = np.sort(x[peaks])[:-1]  # drop the global maximum itself
    mean_other = float(values.mean()) if values.size else 0.0
    return x * (1.0 - mean_other) ** 2


def _center_surround(
    x: np.ndarray, mask: np.ndarray, center: float = 1.0, surround: float = 4.0,
    blurs: _MaskBlur | None = None, surround_value: np.ndarray | None = None,
) -> np.ndarray:
    blurs = blurs or _MaskBlur(mask)
    return np.abs(blurs(x, center) - blurs(x, surround, surround_value))


def _gabor_kernel(theta: float, wavelength: float = 6.0, sigma: float = 3.0) -> np.ndarray:
    half = int(np.ceil(2.5 * sigma))
    y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
    xr = x * np.cos(theta) + y * np.sin(theta)
    envelope = np.exp(-(x * x + y * y) / (2 * sigma * sigma))
    kernel = envelope * np.exp(2j * np.pi * xr / wavelength)
    # Zero-mean real part: a flat patch must give no response.
    return kernel - envelope * (kernel.sum() / envelope.sum())


def _orientation(filled: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Sum of the normalised Gabor energies. Each response is ``signal.fftconvolve(filled, kernel, mode="same",
    axes=(1, 2))`` done by hand with its transform sizes, so that the image's transform is taken once for the
    four kernels (the same values)."""
    kernels = [_gabor_kernel(theta)[None] for theta in np.deg2rad([0.0, 45.0, 90.0, 135.0])]
    size = [filled.shape[a] + kernels[0].shape[a] - 1 for a in (1, 2)]
    fshape = [sp_fft.next_fast_len(n, False) for n in size]
    image = sp_fft.fftn(filled, fshape, axes=(1, 2))
    start = [(n - s) // 2 for n, s in zip(size, filled.shape[1:], strict=True)]
    window = (slice(None), *(slice(a, a + s) for a, s in zip(start, filled.shape[1:], strict=True)))
    total = np.zeros(filled.shape)
    for kernel in kernels:
        full = sp_fft.ifftn(image * sp_fft.fftn(kernel, fshape, axes=(1, 2)), fshape, axes=(1, 2))
        total += itti_normalize(np.abs(full[:, : size[0], : size[1]][window]), mask)
    return total


class _Wrapped:
    """Reads (N, H, W, ...) maps at the object pixels of ``mask`` and at pixels (dy, dx) away from them, wrapping
    round the image edges as ``np.roll`` does (|dy|, |dx| <= ``pad``): maps are padded by wrapping once, so
    each neighbour is a constant offset from the object pixels' flat indices."""

    def __init__(self, mask: np.ndarray, pad: int):
        n, row, col = np.nonzero(mask)
        _, height, width = mask.shape
        self.pad, self._width = pad, width + 2 * pad
        self.here = n * ((height + 2 * pad) * self._width) + (row + pad) * self._width + (col + pad)

    def at(self, dy: int, dx: int) -> np.ndarray:
        """Flat indices, into :meth:`flat` maps, of the pixels (dy, dx) away from the object pixels."""
        return self.here + (dy * self._width + dx)

    def flat(self, x: np.ndarray) -> np.ndarray:
        """``x`` padded by wrapping, flattened over its first three axes."""
        width = ((0, 0), (self.pad, self.pad), (self.pad, self.pad)) + ((0, 0),) * (x.ndim - 3)
        return np.pad(x, width, mode="wrap").reshape(-1, *x.shape[3:])


def _curvature(
    normal: np.ndarray, depth: np.ndarray, mask: np.ndarray, pixel_mm: float, blurs: _MaskBlur | None = None
) -> np.ndarray:
    """RMS curvature from the normal map, evaluated on the object pixels only (the blur reads nothing else)."""
    pixels = _Wrapped(mask, 1)
    normal, depth, flat = pixels.flat(normal), pixels.flat(depth), pixels.flat(mask)
    sq = np.zeros(len(pixels.here))
    for step in ((1, 0), (0, 1)):
        after, before = pixels.at(*step), pixels.at(-step[0], -step[1])
        dn = (normal[after] - normal[before]) / (2 * pixel_mm)
        jump = np.abs(depth[after] - depth[before])
        ok = flat[after] & flat[before] & (jump < 8 * pixel_mm)
        sq += np.where(ok, (dn * dn).sum(axis=-1), 0.0)
    out = np.zeros(mask.shape)
    out[mask] = np.sqrt(sq / 2)
    return (blurs or _MaskBlur(mask))(out, 1.0)


def _edges(
    normal: np.ndarray, depth: np.ndarray, mask: np.ndarray, pixel_mm: float, blurs: _MaskBlur | None = None
) -> np.ndarray:
    """Depth jumps and normal creases towards the four neighbours, evaluated on the object pixels only."""
    far = np.where(mask, depth, depth.max() + 10 * pixel_mm)  # silhouettes are depth discontinuities
    pixels = _Wrapped(mask, 1)
    far, normal, flat, here = pixels.flat(far), pixels.flat(normal), pixels.flat(mask), pixels.here
    edge = np.zeros(len(here))
    for step in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        other = pixels.at(*step)
        jump = np.abs(far[other] - far[here]) > 4 * pixel_mm
        crease = 1.0 - (normal[other] * normal[here]).sum(axis=-1)
        crease = np.where(flat[other], crease, 0.0)
        edge = np.maximum(edge, np.maximum(jump.astype(np.float64), np.clip(crease, 0.0, 1.0)))
    out = np.zeros(mask.shape)
    out[mask] = edge
    return (blurs or _MaskBlur(mask))(out, 1.0)


def _entropy(filled: np.ndarray, mask: np.ndarray, levels: int = 16, sigma: float = 2.0) -> np.ndarray:
    """Windowed entropy on the object pixels (0 on the background). Levels no pixel takes add nothing and are
    skipped; the logarithms are taken on object pixels only."""
    # Only the object pixels are read: the filter covers the object's rows and columns widened by its reach.
    window = _window(mask, _radius(sigma))
    q = np.clip((filled[window] * levels).astype(np.int64), 0, levels - 1)
    inside = mask[window]
    entropy = np.zeros(int(inside.sum()))
    for level in np.unique(q):
        p = _blur((q == level).astype(np.float64), sigma)[inside]
        entropy -= np.where(p > 1e-6, p * np.log2(np.maximum(p, 1e-6)), 0.0)
    out = np.zeros(filled.shape)
    out[mask] = np.clip(entropy / np.log2(levels), 0.0, 1.0)
    return out


def _symmetry(filled: np.ndarray, mask: np.ndarray) -> np.ndarray:
    gx = ndimage.sobel(filled, axis=2)
    gy = ndimage.sobel(filled, axis=1)
    strength = np.log1p(np.hypot(gx, gy))
    pixels = _Wrapped(mask, 6)
    phase, strength = pixels.flat(np.arctan2(gy, gx)), pixels.flat(strength)
    # Votes are summed on the object pixels only (the map is 0 elsewhere); neighbours wrap round the image
    # edges, as np.roll would.
    total = np.zeros(len(pixels.here))
    for radius in (2, 4, 6):
        for alpha in np.arange(8) * np.pi / 8:
            dy, dx = round(radius * np.sin(alpha)), round(radius * np.cos(alpha))
            a = np.arctan2(dy, dx)
            before, after = pixels.at(-dy, -dx), pixels.at(dy, dx)  # x - d, x + d
            t1, t2 = phase[before], phase[after]
            r1, r2 = strength[before], strength[after]
            weight = (1 - np.cos(t1 + t2 - 2 * a)) * (1 - np.cos(t1 - t2)) / 4
            total += np.exp(-2 * np.hypot(dy, dx) / 8) * weight * r1 * r2
    out = np.zeros(filled.shape)
    out[mask] = total
    return out


def _color_opponency(color: np.ndarray, mask: np.ndarray) -> np.ndarray:
    r, g, b = color[..., 0], color[..., 1], color[..., 2]
    rg = _center_surround(r - g, mask)
    by = _center_surround(b - (r + g) / 2, mask)
    return itti_normalize(rg, mask) + itti_normalize(by, mask)


def _dkl(color: np.ndarray, mask: np.ndarray) -> np.ndarray:
    lms = color @ _RGB_TO_LMS.T
    l_, m_, s_ = lms[..., 0], lms[..., 1], lms[..., 2]
    red_green = _center_surround(l_ - m_, mask)
    blue_yellow = _center_surround(s_ - (l_ + m_), mask)
    return itti_normalize(red_green, mask) + itti_normalize(blue_yellow, mask)


def compute_channels(
    intensity: np.ndarray,
    depth: np.ndarray,
    normal: np.ndarray,
    mask: np.ndarray,
    pixel_mm: float,
    channels: tuple[str, ...],
    color: np.ndarray | None = None,
    threads: int | None = None,
) -> dict[str, np.ndarray]:
    """Conspicuity maps (N, H, W) in [0, 1] for the named channels of a view stack.

    Args:
        intensity, depth: (N, H, W) shading in [0, 1] and depth in mm.
        normal: (N, H, W, 3) unit normals.
        mask: (N, H, W) bool object pixels.
        pixel_mm: pixel side, mm.
        channels: names from :data:`ALL_CHANNELS`; colour channels need ``color``.
        color: (N, H, W, 3) RGB in [0, 1], or None.
        threads: channels computed at once (default: the usable cores); the maps do not depend on it.

    Raises:
        InvalidArgumentError: an unknown channel, or a colour channel without ``color``.
    """
    unknown = [name for name in channels if name not in ALL_CHANNELS]
    if unknown:
        raise InvalidArgumentError(f"unknown channel(s) {unknown}; known: {', '.join(ALL_CHANNELS)}")
    if color is None and any(name in COLOR_CHANNELS for name in channels):
        raise InvalidArgumentError(f"channel {next(n for n in channels if n in COLOR_CHANNELS)!r} needs colours")
    intensity = intensity.astype(np.float64)
    normal = normal.astype(np.float64)
    depth = depth.astype(np.float64)
    color = None if color is None else color.astype(np.float64)
    blurs = _MaskBlur(mask)
    shading_4 = blurs.value(intensity, 4.0)  # shared by the background fill and the intensity surround
    filled = fill_background(intensity, mask, 4.0, _blurs=blurs, _value=shading_4)

    def conspicuity(name: str) -> np.ndarray:
        if name == "intensity":
            raw = _center_surround(intensity, mask, blurs=blurs, surround_value=shading_4)
        elif name == "contrast":
            mean = blurs(intensity, 2.0)
            raw = np.sqrt(np.clip(blurs(intensity**2, 2.0) - mean**2, 0.0, None))
        elif name == "orientation":
            raw = _orientation(filled, mask)
        elif name == "curvature":
            raw = _curvature(normal, depth, mask, pixel_mm, blurs)
        elif name == "edges":
            raw = _edges(normal, depth, mask, pixel_mm, blurs)
        elif name == "entropy":
            raw = _entropy(filled, mask)
        elif name == "symmetry":
            raw = _symmetry(filled, mask)
        elif name == "color_opponency":
            raw = _color_opponency(color, mask)
        else:  # "dkl" (the names were checked above)
            raw = _dkl(color, mask)
        return itti_normalize(raw, mask)

    # The channels are independent and their filters (scipy.ndimage, numpy, pocketfft) release the GIL, so
    # threads compute them side by side; each map is the same array as computed alone (the shared blur
    # weights are pure functions of the mask), and the dict keeps the order of ``channels``.
    workers = min(len(channels), usable_cores() if threads is None else int(threads))
    if workers <= 1:
        return {name: conspicuity(name) for name in channels}
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="channels") as pool:
        return dict(zip(channels, pool.map(conspicuity, channels)))
