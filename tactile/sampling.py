"""Where to touch: contour sampling strategies, blind or guided by visual attention.

Every contour plane passes through the object centre and two points (normal (p1 - c) x (p2 - c)):

- ``"blind"``: two distinct random vertices. Never computes saliency.
- ``"guided"``: two distinct random points of the multiview saliency's interest points (the paper's method).
- ``"mesh"``, ``"iss"``: the same with the interest points of mesh saliency or ISS keypoints.

Interest points come from ``Saliency.interest_points(INTEREST_POOL)``. Draws whose points are near-collinear
with the centre (:func:`tactile.contours.plane_through` refuses them) are re-drawn up to ``MAX_DRAWS`` times.
"""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from perception import saliency as attention
from perception.errors import ContourError, SaliencyError
from perception.geometry import ObjectModel
from tactile.contours import Plane, make_contour, plane_through
from tactile.explore import TactileSequence, explore
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Strategy -> the saliency method whose interest points it draws from (None: random vertices).
STRATEGIES: dict[str, str | None] = {"blind": None, "guided": "multiview", "mesh": "mesh", "iss": "iss"}
#: Number of interest points the guided strategies draw pairs from.
INTEREST_POOL = 10
#: Draws per plane (near-collinear pairs) or per contour (planes that miss) before giving up.
MAX_DRAWS = 100


def _check_strategy(strategy: str) -> None:
    if strategy not in STRATEGIES:
        raise ContourError(f"unknown sampling strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")


def _candidates(model: ObjectModel, strategy: str, sal: attention.Saliency | None) -> np.ndarray:
    """The points pairs are drawn from: all vertices (blind) or the interest points of the strategy's method."""
    method = STRATEGIES[strategy]
    if method is None:
        return model.vertices
    if sal is None:
        sal = attention.saliency(model, method)
    elif sal.method != method or sal.model is not model:
        raise SaliencyError(
            f"{model.name}: strategy {strategy!r} needs {method!r} saliency of this object, "
            f"got {sal.method!r} saliency of {sal.model.name}"
        )
    return sal.interest_points(min(INTEREST_POOL, model.n_vertices))


def _draw_plane(model: ObjectModel, points: np.ndarray, rng: np.random.Generator) -> Plane:
    for _ in range(MAX_DRAWS):
        i, j = rng.choice(len(points), size=2, replace=False)
        try:
            return plane_through(model.center, points[i], points[j])
        except ContourError:
            continue  # near-collinear with the centre: draw again
    raise ContourError(
        f"{model.name}: {MAX_DRAWS} draws of two points gave only planes near-collinear with the centre"
    )


def sample_planes(
    model: ObjectModel,
    strategy: str = "blind",
    n: int = 10,
    seed: int | np.random.Generator | None = 0,
    *,
    saliency: attention.Saliency | None = None,
) -> list[Plane]:
    """``n`` contour planes through ``model.center`` chosen by ``strategy`` (see the module docstring).

    Args:
        saliency: a precomputed :class:`~perception.saliency.Saliency` of the strategy's method, to reuse.

    Raises:
        ContourError: unknown strategy, n < 1, or only near-collinear draws.
        SaliencyError: ``saliency`` is of another method or object.
    """
    _check_strategy(strategy)
    if n < 1:
        raise ContourError(f"{model.name}: need n >= 1 planes, got {n}")
    if len(model.vertices) < 2:
        raise ContourError(f"{model.name}: need at least two vertices to draw planes")
    rng = np.random.default_rng(seed)
    points = _candidates(model, strategy, saliency)
    return [_draw_plane(model, points, rng) for _ in range(n)]


def explore_object(
    model: ObjectModel,
    strategy: str = "guided",
    n_contours: int = 10,
    sensor: FSRSensor | None = None,
    probes: int = 25,
    seed: int | np.random.Generator | None = 0,
    saliency: attention.Saliency | None = None,
    *,
    progress: bool = False,
) -> list[TactileSequence]:
    """Explore ``model`` along ``n_contours`` contours chosen by ``strategy``: one tactile sequence each.

    Planes that miss the object (or cut a zero-length contour) are re-drawn, up to ``MAX_DRAWS`` per
    contour. Each sequence records the strategy and its own sensor-noise seed, drawn from ``seed`` after
    its plane; same seed -> same sequences.

    Raises:
        ContourError: unknown strategy, n_contours < 1, probes < 2, or no usable plane after ``MAX_DRAWS``
            draws.
        SaliencyError: ``saliency`` is of another method or object.
    """
    _check_strategy(strategy)
    if n_contours < 1:
        raise ContourError(f"{model.name}: need n_contours >= 1, got {n_contours}")
    if int(probes) != probes or probes < 2:
        raise ContourError(f"{model.name}: probes must be an integer >= 2, got {probes!r}")
    rng = np.random.default_rng(seed)
    points = _candidates(model, strategy, saliency)
    sequences = []
    for _ in tqdm(range(n_contours), desc=f"explore {model.name}", disable=not progress):
        for _ in range(MAX_DRAWS):
            plane = _draw_plane(model, points, rng)
            try:
                contour = make_contour(model, plane, probes)
                break
            except ContourError as exc:
                log.debug("%s: re-drawing a plane (%s)", model.name, exc)
        else:
            raise ContourError(f"{model.name}: {MAX_DRAWS} planes in a row missed the object")
        contour_seed = int(rng.integers(2**31 - 1))
        sequences.append(explore(model, contour, sensor, seed=contour_seed, strategy=strategy))
    return sequences
