"""3D visual attention: where on an object to look (and so, where to touch).

``saliency(model, method)`` gives a :class:`Saliency` with per-vertex scores in [0, 1]:

- ``"multiview"`` (the paper's model): views rendered by ray casting (:mod:`perception.render`), image channels
  (:mod:`perception.channels`), each an Itti conspicuity map, combined as eq. 1 (weighted sum over the sum of
  weights), then pooled per vertex: every object pixel adds its combined value to its hit triangle's three
  vertices with weight (barycentric coordinate x cosine of the viewing angle, so grazing views count least);
  a vertex's score is the weighted mean over all views. Vertices no ray hit (triangles below pixel size)
  take their nearest seen vertex's score. Non-maximum suppression of each view's combined map (local maxima in
  a 9 x 9 window, at least 25 % of the global maximum) gives *fixations*: the peak pixels back-projected to
  the exact surface point of their hit triangle (barycentric, no depth re-projection).
- ``"mesh"``: mesh saliency of Lee, Varshney & Jacobs (2005) (:mod:`perception.mesh_saliency`).
- ``"iss"``: Open3D ISS keypoints spread by a small Gaussian.
- ``"pcl_harris"``, ``"pcl_iss"`` (:data:`PCL_METHODS`): PCL's Harris 3D and ISS 3D keypoints, from the peer
  program ``benchmarks/peers/pcl_keypoints`` (built by ``make peers``; path overridable with
  ``$VISUOTACTILE_PCL_KEYPOINTS``), run in a subprocess with a time limit on the vertices and vertex
  normals (Harris uses the normals). A keypoint set, not a per-vertex map: :attr:`Saliency.keypoints` lists
  the keypoint vertices strongest first (by the detector's response); the keypoint of rank r among K scores
  1 - r / (2K), in (0.5, 1], and every other vertex 0.5 exp(-d^2 / 2 s^2), d its distance to the nearest
  keypoint, s 2 % of the object size (as ``"iss"``), so any keypoint outranks any other vertex. With at least
  n keypoints, ``interest_points(n)`` picks among the keypoints only (by response, spaced as usual); with
  fewer, among all vertices (the keypoints first). All zero when the detector finds no keypoint.

Channel weights are uniform unless given; :func:`fit_channel_weights` learns them from human-marked points.
"""

from __future__ import annotations

import logging
import os
import reprlib
import subprocess
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from numbers import Real
from pathlib import Path

import numpy as np
from scipy import ndimage, sparse
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from perception import mesh_saliency
from perception.atomic import save_figure
from perception.channels import ALL_CHANNELS, COLOR_CHANNELS, GEOMETRY_CHANNELS, compute_channels
from perception.errors import InvalidArgumentError, SaliencyError
from perception.geometry import ObjectModel
from perception.limits import check_count as check_limit
from perception.metrics import auroc
from perception.render import (
    DEFAULT_N_VIEWS,
    DEFAULT_SIZE_PX,
    View,
    ViewStack,
    render_stack,
    render_views,
    surface_points,
    view_directions,
)
from perception.validate import check_count, check_object_model, check_seed

log = logging.getLogger(__name__)

METHODS = ("multiview", "mesh", "iss")
#: Methods run by the PCL keypoint peer program (not in METHODS: they need `make peers`).
PCL_METHODS = ("pcl_harris", "pcl_iss")
#: Environment variable naming the PCL peer program; default :data:`PCL_DEFAULT_BINARY`.
PCL_BINARY_ENV = "VISUOTACTILE_PCL_KEYPOINTS"
PCL_DEFAULT_BINARY = Path(__file__).resolve().parents[1] / "benchmarks" / "peers" / "pcl_keypoints"
#: Time limit (s) of one run of the peer program.
PCL_TIMEOUT_S = 300.0
#: Default separation of interest points, as a fraction of the object size (15 mm at 150 mm; ObjectModel.size, pose-free).
DEFAULT_SEPARATION_FRACTION = 0.1
#: Marked points label vertices within this fraction of the diagonal as "salient" (3 mm at 150 mm).
MARK_RADIUS_FRACTION = 0.02
#: Upper bound on multiview rays (views x pixels): 64 Mi rays is about 1.5 GiB of float32 rays.
MAX_PIXELS = 1 << 26


@dataclass(frozen=True, eq=False)
class Saliency:
    """Per-vertex saliency of one object.

    Attributes:
        model: the object scored.
        scores: (V,) float64 in [0, 1].
        method: one of :data:`METHODS` or :data:`PCL_METHODS`.
        channels_computed: channel names evaluated (multiview only; empty otherwise).
        channels_skipped: channels not evaluated and why, e.g. ``{"dkl": "mesh has no colours"}``.
        channel_maps: per-channel (V,) pooled conspicuity, multiview only.
        weights: the channel weights used (multiview only).
        fixations: (K, 3) surface points (mm) of the per-view non-maximum-suppressed peaks (multiview only).
        keypoints: (K,) int64 vertex indices of the detector's keypoints, strongest first (PCL methods only).
    """

    model: ObjectModel = field(repr=False)
    scores: np.ndarray
    method: str
    channels_computed: tuple[str, ...] = ()
    channels_skipped: dict[str, str] = field(default_factory=dict)
    channel_maps: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    weights: dict[str, float] = field(default_factory=dict)
    fixations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)
    keypoints: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)

    def _candidates(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Candidate surface points and their scores: the keypoints if there are at least ``n``, else the
        vertices, then the fixations (scores interpolated)."""
        if len(self.keypoints) >= n:
            return self.model.vertices[self.keypoints], self.scores[self.keypoints]
        points, scores = self.model.vertices, self.scores
        if len(self.fixations):
            closest, _ = self.model.closest_points(self.fixations)
            _, nearest = cKDTree(self.model.vertices).query(closest)
            points = np.vstack([points, self.fixations])
            scores = np.concatenate([scores, self.scores[nearest]])
        return points, scores

    def interest_points(self, n: int, *, min_distance_mm: float | None = None) -> np.ndarray:
        """(n, 3) surface points (mm), greedily picked by decreasing score, at least ``min_distance_mm`` apart
        (Euclidean; default 10 % of the object size). Where fewer than n fit, the distance is halved and the
        search continues, so the n points always come back. Deterministic (ties broken by index). The
        candidates are the vertices and fixations, or the keypoints when there are at least n of them.

        Raises:
            InvalidArgumentError: n not an integer >= 1 (a fraction or a bool included), n larger than the number
                of candidate points, or a ``min_distance_mm`` that is not a finite number >= 0.
        """
        n = check_count(n, "n (interest points)", self.model.name)
        if min_distance_mm is not None and (not _finite_number(min_distance_mm) or min_distance_mm < 0):
            raise InvalidArgumentError(
                f"{self.model.name}: min_distance_mm must be a finite number >= 0 (mm), got {min_distance_mm!r}"
            )
        points, scores = self._candidates(n)
        if n > len(points):
            raise InvalidArgumentError(
                f"{self.model.name}: cannot pick {n} interest points from {len(points)} candidates "
                f"(the {self.model.n_vertices} vertices and {len(self.fixations)} fixations)"
            )
        distance = (
            DEFAULT_SEPARATION_FRACTION * self.model.size if min_distance_mm is None else float(min_distance_mm)
        )
        order = np.argsort(-scores, kind="stable")
        chosen: list[int] = []
        while len(chosen) < n:
            for index in order:
                if len(chosen) == n:
                    break
                if index in chosen:
                    continue
                if chosen and np.min(np.linalg.norm(points[chosen] - points[index], axis=1)) < distance:
                    continue
                chosen.append(int(index))
            distance = distance / 2 if distance > 1e-9 * self.model.size else 0.0
        return points[chosen].copy()


@dataclass(frozen=True)
class ViewMaps:
    """Per-view multiview maps: the rendered views (stacked), per-channel conspicuity (N, H, W), the combined map
    and its peaks."""

    stack: ViewStack
    channels: dict[str, np.ndarray]
    combined: np.ndarray
    peaks: np.ndarray

    @property
    def views(self) -> list[View]:
        """The N rendered :class:`~perception.render.View` objects (slices of ``stack``)."""
        return self.stack.views


def _finite_number(value) -> bool:
    """Whether ``value`` is a real number (not a bool) with a finite float64 value."""
    if isinstance(value, bool) or not isinstance(value, Real):
        return False
    try:
        return bool(np.isfinite(float(value)))
    except (OverflowError, ValueError, TypeError):
        return False


def _check_weights(
    weights: dict[str, float] | None, channels: tuple[str, ...], name: str
) -> dict[str, float]:
    """The weight of each computed channel (uniform when None; a missing channel weighs 0).

    Raises:
        InvalidArgumentError: not a mapping, an unknown channel, a weight that is not a finite number >= 0, or
            weights of the computed channels that are all zero.
    """
    if weights is None:
        return {c: 1.0 for c in channels}
    if not isinstance(weights, Mapping):
        raise InvalidArgumentError(f"{name}: weights must be a dict of channel -> weight, got {type(weights).__name__}")
    unknown = sorted(map(str, set(weights) - set(ALL_CHANNELS)))
    if unknown:
        raise InvalidArgumentError(f"{name}: unknown channel weight(s) {unknown}; known: {', '.join(ALL_CHANNELS)}")
    bad = {c: v for c, v in weights.items() if not _finite_number(v) or v < 0}
    if bad:
        shown = ", ".join(f"{c!r}: {reprlib.repr(v)}" for c, v in bad.items())
        raise InvalidArgumentError(f"{name}: channel weights must be finite numbers >= 0, got {{{shown}}}")
    values = {c: float(weights.get(c, 0.0)) for c in channels}
    if sum(values.values()) <= 0:
        raise InvalidArgumentError(f"{name}: the weights of the computed channels {channels} sum to zero")
    return values


def _channels_for(model: ObjectModel) -> tuple[tuple[str, ...], dict[str, str]]:
    if model.has_colors:
        return ALL_CHANNELS, {}
    return GEOMETRY_CHANNELS, {c: "mesh has no colours" for c in COLOR_CHANNELS}


def multiview_maps(
    model: ObjectModel,
    *,
    weights: dict[str, float] | None = None,
    n_views: int | None = None,
    size_px: int | None = None,
    seed: int = 0,
) -> ViewMaps:
    """Render the views and compute every channel's conspicuity and the combined map (eq. 1) per view.

    The view sphere (a Fibonacci lattice) is turned by a random rotation drawn from ``seed``, in the object's
    principal frame (:attr:`ObjectModel.principal_frame`), which also sets each image's up direction: turning
    the object turns the views with it, so its saliency does not depend on its pose.

    Raises:
        InvalidArgumentError: ``model`` not an ObjectModel, bad weights or view settings (n_views above the views
            limit of :mod:`perception.limits`).
    """
    check_object_model(model, "multiview_maps")
    seed = check_seed(seed, model.name, allow_none=False)
    if n_views is not None:
        n_views = check_limit("views", check_count(n_views, "n_views", model.name), f"{model.name}: n_views")
    n_views = DEFAULT_N_VIEWS if n_views is None else n_views
    size_px = DEFAULT_SIZE_PX if size_px is None else check_count(size_px, "size_px", model.name, minimum=8)
    if n_views * size_px * size_px > MAX_PIXELS:
        raise InvalidArgumentError(
            f"{model.name}: {n_views} views of {size_px} x {size_px} pixels exceed {MAX_PIXELS:,} rays in all"
        )
    channels, _ = _channels_for(model)
    w = _check_weights(weights, channels, model.name)
    # Eq. 1 divides by the sum of the weights: scaled to a largest weight of 1 first, the sum cannot overflow
    # (weights of 1e308 would make it inf and every score 0) and the weighted mean is the same.
    top = max(w.values())
    w = {c: v / top for c, v in w.items()}
    rotation = Rotation.random(random_state=np.random.default_rng(seed)).as_matrix()
    frame = model.principal_frame
    stack = render_stack(
        model, width=size_px, height=size_px, directions=view_directions(n_views) @ (frame @ rotation).T,
        frame=frame,
    )
    mask = stack.mask
    maps = compute_channels(
        stack.intensity,
        stack.depth,
        stack.normal,
        mask,
        stack.cameras[0].pixel_mm,
        channels,
        color=stack.color,
    )
    combined = sum(w[c] * maps[c] for c in channels) / sum(w.values())
    top = combined.max()
    peaks = (combined == ndimage.maximum_filter(combined, size=(1, 9, 9))) & mask & (combined >= 0.25 * top)
    return ViewMaps(stack, maps, combined, peaks & (top > 0))


def _pool(model: ObjectModel, stack: ViewStack, values: np.ndarray) -> np.ndarray:
    """Per-vertex weighted mean of per-pixel ``values`` (C, N, H, W) -> (C, V); see the module docstring."""
    mask = stack.mask
    ids = stack.triangle_ids[mask]
    bary = stack.barycentric[mask].astype(np.float64)
    cosine = stack.intensity[mask].astype(np.float64)
    weight = (bary * cosine[:, None]).ravel()
    rows = model.triangles[ids].ravel()
    cols = np.repeat(np.arange(len(ids)), 3)
    spread = sparse.csr_matrix((weight, (rows, cols)), shape=(model.n_vertices, len(ids)))
    pixel_values = values[:, mask].T  # (P, C)
    total = spread @ pixel_values
    norm = np.asarray(spread.sum(axis=1)).ravel()
    seen = norm > 1e-12
    pooled = np.zeros((values.shape[0], model.n_vertices))
    pooled[:, seen] = (total[seen] / norm[seen, None]).T
    if not seen.all() and seen.any():
        _, nearest = cKDTree(model.vertices[seen]).query(model.vertices[~seen])
        pooled[:, ~seen] = pooled[:, np.flatnonzero(seen)[nearest]]
    return pooled


def _unit_max(x: np.ndarray) -> np.ndarray:
    x = np.nan_to_num(np.asarray(x, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    top = x.max() if x.size else 0.0
    return np.clip(x / top, 0.0, 1.0) if top > 0 else np.zeros_like(x)


def saliency(
    model: ObjectModel,
    method: str = "multiview",
    *,
    weights: dict[str, float] | None = None,
    n_views: int | None = None,
    size_px: int | None = None,
    seed: int = 0,
) -> Saliency:
    """Per-vertex saliency of ``model`` with the given method (see the module docstring). Deterministic.

    Args:
        model: the object.
        method: one of :data:`METHODS` or :data:`PCL_METHODS`.
        weights: multiview channel weights (missing channels weigh 0); uniform when None.
        n_views, size_px: multiview views and image side (defaults 20 and 128).
        seed: turns the multiview view sphere; the 3D methods do not use it.

    Raises:
        InvalidArgumentError: ``model`` not an ObjectModel (an Open3D mesh or a path: load it with
            ``perception.load_object`` first), unknown method, bad weights (not finite numbers >= 0, or all zero)
            or view settings, a seed that is not a non-negative integer; for ``"mesh"``, a mesh so dense that one
            vertex's neighbourhood does not fit the memory limit (:func:`perception.mesh_saliency.mesh_saliency`).
        SaliencyError: for a PCL method, the peer program absent, failing or past its time limit.

    Examples:
        >>> from perception.shapes import make_object
        >>> attention = saliency(make_object("box", 0), "mesh")
        >>> attention.method, bool(0 <= attention.scores.min() <= attention.scores.max() <= 1)
        ('mesh', True)
        >>> attention.interest_points(3).shape  # surface points (mm) to draw contour planes through
        (3, 3)
    """
    check_object_model(model, "saliency")
    seed = check_seed(seed, model.name, allow_none=False)
    if method not in METHODS + PCL_METHODS:
        raise InvalidArgumentError(
            f"{model.name}: unknown saliency method {method!r}; choose one of {', '.join(METHODS + PCL_METHODS)}"
        )
    if method in PCL_METHODS:
        return _pcl_saliency(model, method)
    if method == "mesh":
        return Saliency(model, _unit_max(mesh_saliency.mesh_saliency(model)), method)
    if method == "iss":
        return Saliency(model, _unit_max(mesh_saliency.iss_saliency(model)), method)
    channels, skipped = _channels_for(model)
    if skipped:
        log.info("%s: colour channels skipped (mesh has no colours)", model.name)
    maps = multiview_maps(model, weights=weights, n_views=n_views, size_px=size_px, seed=seed)
    stack = np.stack([maps.channels[c] for c in channels] + [maps.combined])
    pooled = _pool(model, maps.stack, stack)
    fixations = surface_points(model, maps.stack, maps.peaks)
    return Saliency(
        model,
        _unit_max(pooled[-1]),
        method,
        channels_computed=channels,
        channels_skipped=skipped,
        channel_maps={c: _unit_max(pooled[k]) for k, c in enumerate(channels)},
        weights=_check_weights(weights, channels, model.name),
        fixations=fixations,
    )


# ------------------------------------------------------------------------------------ PCL keypoint peer
def pcl_binary() -> Path:
    """The PCL peer program: ``$VISUOTACTILE_PCL_KEYPOINTS`` when set, else :data:`PCL_DEFAULT_BINARY`."""
    return Path(os.environ.get(PCL_BINARY_ENV) or PCL_DEFAULT_BINARY)


def pcl_available() -> bool:
    """Whether the PCL peer program exists and is executable (the PCL methods can run)."""
    path = pcl_binary()
    return path.is_file() and os.access(path, os.X_OK)


def pcl_keypoints(
    model: ObjectModel, detector: str, *, timeout_s: float = PCL_TIMEOUT_S
) -> tuple[np.ndarray, np.ndarray]:
    """PCL's ``detector`` ("harris" or "iss") on the vertices and vertex normals of ``model``: (K,) int64
    vertex indices and (K,) float64 responses, strongest first (ties by index). Deterministic.

    Raises:
        SaliencyError: unknown detector, the program absent, failing (a crash included) or past ``timeout_s``,
            or output that does not match the input.
    """
    if detector not in ("harris", "iss"):
        raise InvalidArgumentError(f"{model.name}: unknown PCL detector {detector!r}; choose harris or iss")
    binary = pcl_binary()
    if not pcl_available():
        raise SaliencyError(
            f"PCL keypoints unavailable: {binary} is not an executable file; build it with `make peers` "
            f"(installs libpcl-dev with apt-get when root), or set ${PCL_BINARY_ENV} to the program"
        )
    normals = np.nan_to_num(model.vertex_normals, nan=0.0, posinf=0.0, neginf=0.0)
    with tempfile.TemporaryDirectory(prefix="visuotactile-pcl-") as tmp:
        cloud, keys, resp = (Path(tmp) / name for name in ("cloud.xyz", "keys.txt", "responses.txt"))
        np.savetxt(cloud, np.hstack([model.vertices, normals]), fmt="%.9g")
        try:
            done = subprocess.run([str(binary), detector, str(cloud), str(keys), str(resp)],
                                  capture_output=True, text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired as exc:
            raise SaliencyError(f"{model.name}: PCL {detector} ran past its time limit ({timeout_s:g} s)") from exc
        except OSError as exc:
            raise SaliencyError(f"{model.name}: cannot run {binary} ({exc})") from exc
        if done.returncode != 0:
            why = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
            raise SaliencyError(f"{model.name}: PCL {detector} failed ({why}; exit status {done.returncode})")
        try:
            index = np.loadtxt(keys, dtype=np.int64, ndmin=1) if keys.stat().st_size else np.zeros(0, np.int64)
            response = np.loadtxt(resp, dtype=np.float64, ndmin=1) if resp.stat().st_size else np.zeros(0)
        except (OSError, ValueError) as exc:
            raise SaliencyError(f"{model.name}: unreadable PCL {detector} output ({exc})") from exc
    if (len(index) != len(response) or len(np.unique(index)) != len(index)
            or (len(index) and (index.min() < 0 or index.max() >= model.n_vertices))):
        raise SaliencyError(f"{model.name}: PCL {detector} output does not match the {model.n_vertices} vertices")
    response = np.nan_to_num(response, nan=-np.inf)
    order = np.lexsort((index, -response))
    return index[order], response[order]


def _pcl_saliency(model: ObjectModel, method: str) -> Saliency:
    """A PCL method's :class:`Saliency`: ranked keypoints and the tiered spread map (module docstring)."""
    index, _ = pcl_keypoints(model, method.removeprefix("pcl_"))
    scores = np.zeros(model.n_vertices)
    if len(index):
        d, _ = cKDTree(model.vertices[index]).query(model.vertices)
        s = mesh_saliency.ISS_SPREAD_FRACTION * model.size
        scores = 0.5 * np.exp(-(d * d) / (2 * s * s))
        scores[index] = 1.0 - np.arange(len(index)) / (2 * len(index))
    else:
        log.warning("%s: PCL %s found no keypoints; interest points fall back to vertex order", model.name, method)
    return Saliency(model, scores, method, keypoints=index)


# ------------------------------------------------------------------------------------ learned weights
def load_marked_points(path: str | Path) -> np.ndarray:
    """(K, 3) float64 human-marked points from a text file of ``x y z`` lines (mm; ``#`` comments allowed).

    Raises:
        SaliencyError: missing or unreadable file, wrong column count, non-finite values, or no points.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SaliencyError(f"{path}: cannot read marked points ({exc})") from exc
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
        except ValueError as exc:
            raise SaliencyError(f"{path}:{number}: not a number in {line!r}") from exc
        if len(values) != 3 or not np.all(np.isfinite(values)):
            raise SaliencyError(f"{path}:{number}: expected three finite numbers 'x y z', got {line!r}")
        rows.append(values)
    if not rows:
        raise SaliencyError(f"{path}: no marked points")
    return np.asarray(rows, dtype=np.float64)


def _auc(values: np.ndarray, positive: np.ndarray) -> float:
    """ROC area under the curve of ``values`` separating ``positive`` from the rest (ties count half)."""
    if positive.all() or not positive.any():
        return 0.5
    return auroc(values[positive], values[~positive])


def fit_channel_weights(
    models: list[ObjectModel],
    ground_truth_points: list[np.ndarray | str | Path],
    *,
    radius_mm: float | None = None,
    n_views: int | None = None,
    size_px: int | None = None,
    seed: int = 0,
) -> dict[str, float]:
    """Learn multiview channel weights from human-marked points (one (K, 3) array or file per model).

    A vertex is "marked" if it is the nearest vertex of a marked point or lies within ``radius_mm``
    (default 2 % of the object size) of one. Each channel's weight is its Somers' D, 2 AUC - 1 (clipped at 0),
    for ranking marked above unmarked vertices by its pooled per-vertex conspicuity, averaged over the
    models, then normalised to sum 1. ``n_views``, ``size_px`` and ``seed`` are passed to :func:`saliency`. A rank measure, not a regression: the channels are strongly
    correlated (on simple shapes several rank the same vertices), and least-squares fits then pick an
    arbitrary one of them. Channels computed for only some models (colour) are left out.

    Raises:
        SaliencyError: mismatched lists, bad marked points, or no channel ranking the marks above chance.
    """
    if len(models) != len(ground_truth_points) or not models:
        raise SaliencyError(
            f"need one set of marked points per model, got {len(models)} models and {len(ground_truth_points)} sets"
        )
    maps, labels = [], []
    for model, marks in zip(models, ground_truth_points, strict=True):
        points = load_marked_points(marks) if isinstance(marks, (str, Path)) else np.asarray(marks, float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 or not np.isfinite(points).all():
            raise SaliencyError(f"{model.name}: marked points must be a non-empty finite (K, 3) array")
        radius = MARK_RADIUS_FRACTION * model.size if radius_mm is None else radius_mm
        distance, _ = cKDTree(points).query(model.vertices)
        positive = distance <= radius
        positive[cKDTree(model.vertices).query(points)[1]] = True
        labels.append(positive)
        maps.append(saliency(model, "multiview", n_views=n_views, size_px=size_px, seed=seed).channel_maps)
    channels = [c for c in ALL_CHANNELS if all(c in m for m in maps)]
    score = np.array([np.mean([_auc(m[c], y) for m, y in zip(maps, labels, strict=True)]) for c in channels])
    w = np.clip(2 * score - 1, 0.0, None)
    if w.sum() <= 0:
        raise SaliencyError("no channel ranks the marked points above chance; keep uniform weights")
    return {c: float(v / w.sum()) for c, v in zip(channels, w, strict=True)}


# ---------------------------------------------------------------------------------------------- figures
def plot_channels(
    model: ObjectModel,
    path: str | Path,
    *,
    n_rows: int = 3,
    seed: int = 0,
    n_views: int | None = None,
    size_px: int | None = None,
) -> Path:
    """PNG grid: for ``n_rows`` views (those showing the most object), the shading, every channel's
    conspicuity map and the combined map with its non-maximum-suppressed peaks (red dots). Returns the path.
    ``n_views`` and ``size_px`` as in :func:`saliency`."""
    maps = multiview_maps(model, seed=seed, n_views=n_views, size_px=size_px)
    rows = np.argsort(-maps.stack.mask.sum(axis=(1, 2)), kind="stable")[:n_rows]
    columns = ["shading", *maps.channels, "combined"]
    fig = _figure(figsize=(1.8 * len(columns), 1.9 * len(rows)))
    axes = fig.subplots(len(rows), len(columns), squeeze=False)
    for r, k in enumerate(rows):
        images = [maps.stack.intensity[k], *(maps.channels[c][k] for c in maps.channels), maps.combined[k]]
        for c, (title, image) in enumerate(zip(columns, images, strict=True)):
            ax = axes[r, c]
            ax.imshow(image, cmap="gray" if c == 0 else "inferno", vmin=0, vmax=max(float(image.max()), 1e-9))
            if title == "combined":
                peak_rows, peak_cols = np.nonzero(maps.peaks[k])
                ax.plot(peak_cols, peak_rows, "o", color="red", markersize=2)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=8)
    fig.suptitle(f"{model.name}: multiview channels (conspicuity) and eq. 1 combination", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=110)
    return path


def _figure(figsize: tuple[float, float]):
    """A ``matplotlib.figure.Figure`` on an Agg canvas: no pyplot, the user's backend is left alone."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def plot_saliency(sal: Saliency, path: str | Path, *, n_points: int = 10, size_px: int = 256) -> Path:
    """PNG of the per-vertex scores on the mesh from two opposite views (shaded, colour = score) with the
    ``n_points`` interest points marked where visible. Returns the path."""
    import matplotlib
    from matplotlib.cm import ScalarMappable

    from perception.render import interpolate_values, visible

    model = sal.model
    points = sal.interest_points(n_points)
    directions = np.array([[1.0, -1.0, 0.8], [-1.0, 1.0, -0.8]])
    views = render_views(model, width=size_px, height=size_px, directions=directions)
    fig = _figure(figsize=(8, 4.3))
    axes = fig.subplots(1, 2)
    cmap = matplotlib.colormaps["inferno"]
    for ax, view in zip(axes, views, strict=True):
        colour = cmap(interpolate_values(model, view, sal.scores))[..., :3]
        image = colour * (0.35 + 0.65 * view.intensity[..., None])
        image[~view.mask] = 1.0
        ax.imshow(image)
        seen = visible(view, points, 0.01 * model.size)
        pix = view.camera.project(points[seen])
        ax.plot(
            pix[:, 0], pix[:, 1], "o", markerfacecolor="none", markeredgecolor="cyan", markersize=9, mew=2
        )
        ax.set_axis_off()
    fig.suptitle(f"{model.name}: {sal.method} saliency, {n_points} interest points (cyan)", fontsize=10)
    fig.colorbar(ScalarMappable(cmap=cmap), ax=axes, shrink=0.8, label="score")
    path = Path(path)
    save_figure(fig, path, dpi=110)
    return path
