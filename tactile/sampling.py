"""Where to touch: contour sampling strategies, blind or guided by visual attention.

Every contour plane passes through the object centre and two points (normal (p1 - c) x (p2 - c)):

- ``"blind"``: two distinct random vertices. Never computes saliency.
- ``"guided"``: two distinct points of the multiview saliency's interest points (the paper's method).
- ``"mesh"``, ``"iss"``: the same with the interest points of mesh saliency or ISS keypoints.
- ``"pcl_harris"``, ``"pcl_iss"``: the same with PCL's Harris 3D or ISS 3D keypoints, strongest first
  (:data:`perception.saliency.PCL_METHODS`; they need the peer program that ``make peers`` builds, and
  raise :class:`~perception.errors.SaliencyError` naming it when it is absent).

Interest points come from ``Saliency.interest_points(INTEREST_POOL)``. The guided strategies take their pairs
without repeats (:class:`PairOrder`): ten points give at most 45 planes, and 24 draws with repeats touched about
one contour in four twice (a second touch of the same contour tells nothing new). Blind draws of two random vertices
repeat a pair too rarely to matter; those whose points are near-collinear with the centre
(:func:`tactile.contours.plane_through` refuses them) are re-drawn up to ``MAX_DRAWS`` times.
Touching along the planes drawn here is :mod:`tactile.touching`.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from perception import saliency as attention
from perception.errors import ContourError, InvalidArgumentError, SaliencyError
from perception.geometry import ObjectModel
from perception.validate import check_count, check_seed
from tactile.contours import Plane, plane_through

#: Strategy -> the saliency method whose interest points it draws from (None: random vertices).
STRATEGIES: dict[str, str | None] = {"blind": None, "guided": "multiview", "mesh": "mesh", "iss": "iss",
                                     "pcl_harris": "pcl_harris", "pcl_iss": "pcl_iss"}
#: The two strategies the paper compares (and every experiment part but attention).
PAPER_STRATEGIES = ("guided", "blind")
#: Number of interest points the guided strategies draw pairs from.
INTEREST_POOL = 10
#: How guided strategies draw their pairs; stores and model caches of guided contours record it (stores made
#: when pairs were drawn with repeats lack it, so they are neither resumed nor reused with today's rows).
GUIDED_PAIRS = "without repeats"
#: Planes through the centre closer than this (degrees) are one contour to a guided strategy: 100 mm from the
#: centre they lie within 1.7 mm, a tenth of the default 20 mm pad.
SAME_PLANE_DEG = 1.0
#: Draws per plane (near-collinear pairs) or per contour (planes that miss) before giving up.
MAX_DRAWS = 100
#: An object whose RMS distance from its best-fit plane is below this fraction of its size is flat.
FLAT_TOLERANCE = 1e-9


def check_strategy(strategy: str) -> None:
    if strategy not in STRATEGIES:
        raise InvalidArgumentError(f"unknown sampling strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")


def is_guided(strategy: str) -> bool:
    """Whether ``strategy`` draws its pairs from interest points (without repeats) rather than random vertices."""
    return STRATEGIES[strategy] is not None


def pair_setting(strategies) -> dict:
    """``{"guided_pairs": GUIDED_PAIRS}`` when a strategy (one name or several) draws interest-point pairs, else
    ``{}`` (blind stores keep their identity).

    Raises:
        InvalidArgumentError: an unknown strategy.
    """
    strategies = (strategies,) if isinstance(strategies, str) else tuple(strategies)
    for strategy in strategies:
        check_strategy(strategy)
    return {"guided_pairs": GUIDED_PAIRS} if any(is_guided(s) for s in strategies) else {}


def check_not_flat(model: ObjectModel) -> None:
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


def candidates(model: ObjectModel, strategy: str, sal: attention.Saliency | None) -> np.ndarray:
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


def draw_plane(model: ObjectModel, points: np.ndarray, rng: np.random.Generator) -> Plane:
    for _ in range(MAX_DRAWS):
        i, j = rng.choice(len(points), size=2, replace=False)
        try:
            return plane_through(model.center, points[i], points[j])
        except ContourError:
            continue  # near-collinear with the centre: draw again
    raise ContourError(
        f"{model.name}: {MAX_DRAWS} draws of two points gave only planes near-collinear with the centre (seen from "
        "its centre the object lies along one line: a needle, or parts far apart on either side of the centre; "
        "touch each part as an object of its own)"
    )


def pair_planes(model: ObjectModel, points: np.ndarray) -> list[Plane]:
    """The distinct planes through ``model.center`` and a pair of ``points``: pairs in row-major order (i < j),
    leaving out those near-collinear with the centre and those whose plane is within ``SAME_PLANE_DEG`` of an
    earlier one (three points coplanar with the centre give one plane, not three)."""
    planes: list[Plane] = []
    normals = np.empty((0, 3))
    cos_same = np.cos(np.radians(SAME_PLANE_DEG))
    for i in range(len(points)):
        for j in range(i + 1, len(points)):
            try:
                plane = plane_through(model.center, points[i], points[j])
            except ContourError:
                continue  # near-collinear with the centre: no plane
            if (np.abs(normals @ plane.normal) < cos_same).all():
                planes.append(plane)
                normals = np.vstack((normals, plane.normal))
    return planes


class PairOrder:
    """``planes`` (the usable pairs of a guided strategy) in a seeded order without repeats.

    Position ``k`` is ``planes[perm_c[k % P]]``, where ``c = k // P`` and ``perm_c`` is the permutation drawn from
    ``(seed, c)``: every plane comes once before any comes again, and position ``k`` depends only on ``(seed, k)``
    (a store makes its rows independently). Positions go on for ever; iterating gives the first cycle.

    Raises:
        ContourError: ``planes`` is empty (``name`` says which object).
        InvalidArgumentError: a seed that is not an integer in [0, 2**63); a position that is not an integer >= 0.
    """

    def __init__(self, planes: list[Plane], seed: int, name: str = "object") -> None:
        planes = [] if planes is None else list(planes)
        if not planes:
            raise ContourError(f"{name}: no pair of its interest points gives a plane through the centre that cuts it")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
            raise InvalidArgumentError(f"{name}: pair order seed must be an integer in [0, 2**63), got {seed!r}")
        self.planes, self.seed, self.name = planes, int(seed), name
        self._cycle: tuple[int, np.ndarray] = (-1, np.empty(0, np.int64))  # the last cycle's permutation

    def __len__(self) -> int:
        return len(self.planes)

    def __iter__(self) -> Iterator[Plane]:
        return (self[k] for k in range(len(self.planes)))

    def __getitem__(self, k: int) -> Plane:
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
            raise InvalidArgumentError(f"{self.name}: pair order positions are integers >= 0, got {k!r}")
        cycle, i = divmod(int(k), len(self.planes))
        if self._cycle[0] != cycle:  # positions are mostly read in order: one cycle kept, memory stays bounded
            self._cycle = (cycle, np.random.default_rng([self.seed, cycle]).permutation(len(self.planes)))
        return self.planes[self._cycle[1][i]]


def sample_planes(
    model: ObjectModel,
    strategy: str = "blind",
    n: int = 10,
    seed: int | np.random.Generator | None = 0,
    *,
    saliency: attention.Saliency | None = None,
) -> list[Plane]:
    """``n`` contour planes through ``model.center`` chosen by ``strategy`` (see the module docstring); guided
    strategies repeat a plane only after all their pairs (of those not near-collinear) have been used.

    Args:
        saliency: a precomputed :class:`~perception.saliency.Saliency` of the strategy's method, to reuse.

    Raises:
        InvalidArgumentError: unknown strategy, n not an integer >= 1, a seed that is not a non-negative integer
            or Generator. ContourError: only near-collinear draws or pairs.
        SaliencyError: ``saliency`` is of another method or object.
    """
    check_strategy(strategy)
    n = check_count(n, "n", model.name)
    seed = check_seed(seed, model.name)
    if len(model.vertices) < 2:
        raise ContourError(f"{model.name}: need at least two vertices to draw planes")
    rng = np.random.default_rng(seed)
    points = candidates(model, strategy, saliency)
    if not is_guided(strategy):
        return [draw_plane(model, points, rng) for _ in range(n)]
    order = PairOrder(pair_planes(model, points), int(rng.integers(2**63)), model.name)
    return [order[k] for k in range(n)]


def __getattr__(name: str):
    # ``explore_object`` moved to :mod:`tactile.touching` (the one touching road); scripts still import it here.
    if name == "explore_object":
        from tactile.touching import explore_object

        return explore_object
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["FLAT_TOLERANCE", "GUIDED_PAIRS", "INTEREST_POOL", "MAX_DRAWS", "PAPER_STRATEGIES", "SAME_PLANE_DEG", "STRATEGIES", "PairOrder", "candidates",
           "check_not_flat", "check_strategy", "draw_plane", "is_guided", "pair_planes", "pair_setting", "sample_planes"]
