"""Where to touch: contour sampling strategies, blind or guided by visual attention.

Every contour plane passes through the object centre and two points (normal (p1 - c) x (p2 - c)):

- ``"blind"``: two distinct random vertices. Never computes saliency.
- ``"guided"``: two distinct random points of the multiview saliency's interest points (the paper's method).
- ``"mesh"``, ``"iss"``: the same with the interest points of mesh saliency or ISS keypoints.
- ``"pcl_harris"``, ``"pcl_iss"``: the same with PCL's Harris 3D or ISS 3D keypoints, strongest first
  (:data:`perception.saliency.PCL_METHODS`; they need the peer program that ``make peers`` builds, and
  raise :class:`~perception.errors.SaliencyError` naming it when it is absent).

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
from perception.validate import check_count, check_seed
from tactile.contours import Contour, Plane, make_contour, plane_through
from tactile.explore import TactileSequence, explore
from tactile.sensor import FSRSensor

log = logging.getLogger(__name__)

#: Strategy -> the saliency method whose interest points it draws from (None: random vertices).
STRATEGIES: dict[str, str | None] = {"blind": None, "guided": "multiview", "mesh": "mesh", "iss": "iss",
                                     "pcl_harris": "pcl_harris", "pcl_iss": "pcl_iss"}
#: Number of interest points the guided strategies draw pairs from.
INTEREST_POOL = 10
#: Draws per plane (near-collinear pairs) or per contour (planes that miss) before giving up.
MAX_DRAWS = 100
#: An object whose RMS distance from its best-fit plane is below this fraction of its size is flat.
FLAT_TOLERANCE = 1e-9


def _check_strategy(strategy: str) -> None:
    if strategy not in STRATEGIES:
        raise ContourError(f"unknown sampling strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")


def _check_not_flat(model: ObjectModel) -> None:
    """Refuse an object whose vertices all lie in one plane (a flat plate): every plane through its centre
    and two of its points is the plate's own plane, which holds the surface instead of cutting it."""
    centred = model.vertices - model.center
    # Smallest singular value of the centred vertices = the RMS distance from the best-fit plane x sqrt(V).
    thickness = np.linalg.svd(centred / max(model.size, 1e-300), compute_uv=False)[-1]
    if thickness <= FLAT_TOLERANCE * np.sqrt(model.n_vertices):
        raise ContourError(
            f"{model.name}: the object is flat (all {model.n_vertices} vertices lie in one plane), so every "
            "plane through its centre and two of its points is its own plane and cuts no contour; "
            "give it a thickness (e.g. extrude the plate into a solid)"
        )


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
        ContourError: unknown strategy, n not an integer >= 1, a seed that is not a non-negative integer or
            Generator, or only near-collinear draws.
        SaliencyError: ``saliency`` is of another method or object.
    """
    _check_strategy(strategy)
    n = check_count(n, "n", model.name, ContourError)
    seed = check_seed(seed, model.name, ContourError)
    if len(model.vertices) < 2:
        raise ContourError(f"{model.name}: need at least two vertices to draw planes")
    rng = np.random.default_rng(seed)
    points = _candidates(model, strategy, saliency)
    return [_draw_plane(model, points, rng) for _ in range(n)]


def draw_contour(
    model: ObjectModel, points: np.ndarray, rng: np.random.Generator, probes: int = 25, cache: dict | None = None
) -> Contour:
    """One contour through ``model.center`` and two of ``points`` drawn with ``rng``; planes that miss the
    object (or cut a zero-length contour) are re-drawn, up to ``MAX_DRAWS`` times.

    ``cache`` (a dict kept by the caller for one model and ``probes``) maps planes already cut to their
    contour or failure: guided strategies draw from 10 interest points, so a few hundred draws repeat the
    same 90 ordered pairs, and a repeated plane is cut once. The draws from ``rng`` are the same either way.

    Raises:
        ContourError: ``MAX_DRAWS`` planes in a row missed the object.
    """
    for _ in range(MAX_DRAWS):
        plane = _draw_plane(model, points, rng)
        key = (plane.point.tobytes(), plane.normal.tobytes())
        found = cache.get(key) if cache is not None else None
        if found is None:
            try:
                found = make_contour(model, plane, probes)
            except ContourError as exc:
                found = exc
            if cache is not None:
                cache[key] = found
        if isinstance(found, Contour):
            return found
        log.debug("%s: re-drawing a plane (%s)", model.name, found)
    raise ContourError(f"{model.name}: {MAX_DRAWS} planes in a row missed the object")


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
        ContourError: unknown strategy, n_contours not an integer >= 1, probes not an integer >= 2, a seed
            that is not a non-negative integer or Generator, a flat object, or no usable plane after
            ``MAX_DRAWS`` draws.
        SaliencyError: ``saliency`` is of another method or object.
    """
    _check_strategy(strategy)
    n_contours = check_count(n_contours, "n_contours", model.name, ContourError)
    probes = check_count(probes, "probes", model.name, ContourError, minimum=2)
    seed = check_seed(seed, model.name, ContourError)
    _check_not_flat(model)
    rng = np.random.default_rng(seed)
    points = _candidates(model, strategy, saliency)
    sequences, cache = [], {}
    for _ in tqdm(range(n_contours), desc=f"explore {model.name}", disable=not progress):
        contour = draw_contour(model, points, rng, probes, cache)
        contour_seed = int(rng.integers(2**31 - 1))
        sequences.append(explore(model, contour, sensor, seed=contour_seed, strategy=strategy))
    return sequences
