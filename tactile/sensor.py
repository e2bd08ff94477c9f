"""The virtual FSR tactile array: a square pad of taxels pressed on the surface by ray casting.

At each probe the pad lies in the tangent plane (x = tangent, y = normal x tangent), centred at the
probe. Each taxel casts one ray from a stand-off ``h`` above the pad along the outward normal back
towards the surface; ``gap = t_hit - h`` is the distance from the pad plane to the surface (0 where they
touch, negative where the surface pokes through the pad). All taxels of a batch of probes go into one
``RaycastingScene.cast_rays`` call. Where the pad penetrates (a concave spot) it shrinks, keeping its
taxel count (finer pitch), and only those probes are cast again. Before shrinking, a penetrating pad
first tries to settle: a rigid pad pressed on a rough surface (a camera reconstruction's millimetre
ripples, a coarse mesh's blended vertex normal at an edge) tilts onto the surface's mean plane under it
and rests on the highest point; it keeps that pose when the rise stays within ``settle_mm`` and nothing
then pokes through. A real concavity needs a larger rise, so the pad shrinks into it as before.

Frames are indexed ``[row, col]``: columns run along the pad x axis (the contour tangent), rows along
the pad y axis, both increasing with the index.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from numbers import Integral, Real

import numpy as np
import open3d as o3d

from perception.errors import SensorSpecError
from perception.geometry import MAX_COORDINATE_MM, ObjectModel
from perception.validate import check_seed
from tactile.contours import orthonormal_tangents

log = logging.getLogger(__name__)

#: Upper bound on rays per ``cast_rays`` call (bounds memory; 2**20 rays is 24 MiB of float32 input).
MAX_RAYS_PER_CAST = 1 << 20
_rays_cast = 0  # by this process's sensors, survey, shrink and settle casts included (:func:`rays_cast`)


def rays_cast() -> int:
    """Rays this process's sensors have cast so far, every pass of the adaptive pad included: the ray-casting work
    that generation does, against which ``benchmarks.dataset`` sets its raw ``cast_rays`` rate."""
    return _rays_cast

MODES = ("gap", "contact")
#: Lengths (mm) of a spec lie below MAX_LENGTH_MM: beyond 10 m float32 ray casting loses the micrometres the
#: gaps need (a 1e39 mm range or stand-off is infinite in float32); the pad side lies above MIN_LENGTH_MM.
MIN_LENGTH_MM, MAX_LENGTH_MM = 1e-6, 1e4
#: Pressure-unit settings (stiffness, saturation, contact noise) lie within [1e-30, 1e30], where float32
#: readings and the ADC step saturation / (2**bits - 1) are finite and non-zero.
MIN_PRESSURE, MAX_PRESSURE = 1e-30, 1e30


def _finite(value: Real) -> bool:
    """True for a finite real number; an integer too large for a float (np.isfinite raises on it) is not."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def unit_taxel_grid(rows: int, cols: int) -> np.ndarray:
    """(rows * cols, 2) taxel-centre (x, y) on a pad of unit side centred at 0, row-major (x along cols)."""
    x = (np.arange(cols) + 0.5) / cols - 0.5
    y = (np.arange(rows) + 0.5) / rows - 0.5
    yy, xx = np.meshgrid(y, x, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


@dataclass(frozen=True)
class FSRSensor:
    """Specification of a virtual FSR tactile array, and :meth:`press` to read it.

    Attributes:
        rows, cols: taxel counts (pad y and x).
        side_mm: pad side before any shrinking, mm.
        min_side_mm: smallest side the adaptive pad shrinks to, mm.
        mode: ``"gap"``: the distance image (mm from each taxel to the surface, clipped to
            [0, ``range_mm``]; a flat surface reads all zeros). ``"contact"``: pressure
            ``stiffness * max(0, indent_mm - gap)`` (0 where the gap reads the range: nothing sensed),
            saturated at ``saturation`` and quantised to ``adc_bits``.
        range_mm: sensing range: the reading where a ray misses or the surface is further away.
        standoff_mm: height above the pad where taxel rays start. Surface poking through the pad by
            more than this reads as exactly ``-standoff_mm`` on watertight meshes (the ray starts inside).
        indent_mm: indentation depth delta of the contact model, mm.
        stiffness: pressure per mm of indentation (contact mode).
        saturation: largest pressure the taxel reports (contact mode).
        adc_bits: quantisation of the pressure (contact mode), levels 2**bits - 1 over [0, saturation].
        noise_std: Gaussian taxel noise (mm in gap mode, pressure units in contact mode), 0 for none.
        dead_taxel_rate: fraction of taxels that read nothing (range in gap mode, 0 in contact mode);
            drawn once per :meth:`press` call.
        penetration_eps_mm: the pad counts as penetrating where min(gap) < -eps. It absorbs the
            tessellation (the pad follows the interpolated normal, so flat facets near the probe poke
            through by a fraction of a millimetre on coarse meshes) and stands for the skin's give.
        shrink_factor: the adaptive pad's sides form the ladder side_mm * shrink_factor**k (k >= 0),
            never below min_side_mm; in (0, 1).
        settle_mm: how far above its probe a penetrating pad may come to rest when it settles on the
            least-squares plane of the surface under it (see the module docstring), mm; 0 turns settling
            off. It stands for the pad's compliance to roughness, not to shape: a concavity deeper than
            this still shrinks the pad.
        survey_taxels: before the full-resolution cast, an adaptive press surveys the pad with a
            survey_taxels x survey_taxels subset of its taxels (shrinking on that cheap grid first), so
            most probes are cast at full resolution once, and that cast skips the survey's taxels (read
            at the same side already); 0 turns the survey off.

    Raises:
        SensorSpecError: a non-positive size, ``min_side_mm`` > ``side_mm``, an unknown mode, a rate or
            factor out of range, or a non-numeric value.

    Examples:
        >>> import numpy as np
        >>> from perception.primitives import sphere
        >>> sensor = FSRSensor(rows=8, cols=8)
        >>> FSRSensor.from_spec(sensor.spec()) == sensor  # a plain-data spec, stored with data and models
        True
        >>> ball = sphere(40.0, 4)
        >>> top = ball.vertices[[np.argmax(ball.vertices[:, 2])]]  # press the pad on the top of the sphere
        >>> frames, sides = sensor.press(ball, top, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
        >>> frames.shape, bool(frames.min() >= 0), float(sides[0]) == sensor.side_mm
        ((1, 8, 8), True, True)
    """

    rows: int = 32
    cols: int = 32
    side_mm: float = 20.0
    min_side_mm: float = 5.0
    mode: str = "gap"
    range_mm: float = 10.0
    standoff_mm: float = 5.0
    indent_mm: float = 1.0
    stiffness: float = 1.0
    saturation: float = 1.0
    adc_bits: int = 12
    noise_std: float = 0.0
    dead_taxel_rate: float = 0.0
    penetration_eps_mm: float = 0.2
    shrink_factor: float = 0.8
    settle_mm: float = 1.0
    survey_taxels: int = 8

    def __post_init__(self) -> None:
        for name in ("rows", "cols", "adc_bits", "survey_taxels"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Integral):
                raise SensorSpecError(f"FSRSensor.{name} must be an integer, got {value!r}")
        for name in ("rows", "cols"):
            if not 1 <= getattr(self, name) <= 1024:
                raise SensorSpecError(
                    f"FSRSensor.{name} must be in 1..1024 taxels, got {getattr(self, name)}"
                )
        if not 0 <= self.survey_taxels <= 1024:
            raise SensorSpecError(f"FSRSensor.survey_taxels must be in 0..1024, got {self.survey_taxels}")
        if not 1 <= self.adc_bits <= 32:
            raise SensorSpecError(f"FSRSensor.adc_bits must be in 1..32, got {self.adc_bits}")
        if self.mode not in MODES:
            raise SensorSpecError(f"FSRSensor.mode must be one of {MODES}, got {self.mode!r}")
        positive = ("side_mm", "min_side_mm", "range_mm", "standoff_mm", "stiffness", "saturation")
        non_negative = ("indent_mm", "noise_std", "dead_taxel_rate", "penetration_eps_mm", "settle_mm")
        for name in (*positive, *non_negative, "shrink_factor"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, Real) or not _finite(value):
                raise SensorSpecError(f"FSRSensor.{name} must be a finite number, got {value!r}")
        for name in positive:
            if getattr(self, name) <= 0:
                raise SensorSpecError(f"FSRSensor.{name} must be > 0, got {getattr(self, name)}")
        for name in non_negative:
            if getattr(self, name) < 0:
                raise SensorSpecError(f"FSRSensor.{name} must be >= 0, got {getattr(self, name)}")
        lengths = ["side_mm", "min_side_mm", "range_mm", "standoff_mm", "indent_mm", "penetration_eps_mm", "settle_mm"]
        pressures = ["stiffness", "saturation"]
        (lengths if self.mode == "gap" else pressures).append("noise_std")
        for name in lengths:
            value = getattr(self, name)
            # Only the pad's own size has a floor: below it, float32 taxel offsets collapse to one point.
            floor = MIN_LENGTH_MM if name in ("side_mm", "min_side_mm") else 0.0
            if value > MAX_LENGTH_MM or value < floor:
                raise SensorSpecError(f"FSRSensor.{name} must lie in [{floor:g}, {MAX_LENGTH_MM:g}] mm, got {value!r}")
        for name in pressures:
            value = getattr(self, name)
            if value > MAX_PRESSURE or 0 < value < MIN_PRESSURE:
                raise SensorSpecError(
                    f"FSRSensor.{name} must lie in [{MIN_PRESSURE:g}, {MAX_PRESSURE:g}] pressure units, got {value!r}"
                )
        if self.min_side_mm > self.side_mm:
            raise SensorSpecError(
                f"FSRSensor.min_side_mm ({self.min_side_mm}) must not exceed side_mm ({self.side_mm})"
            )
        if self.standoff_mm <= self.penetration_eps_mm:
            raise SensorSpecError(
                f"FSRSensor.standoff_mm ({self.standoff_mm}) must exceed penetration_eps_mm ({self.penetration_eps_mm}): "
                "surface poking through the pad reads at most the stand-off deep, so the pad would never count as "
                "penetrating and never settle or shrink"
            )
        if not 0 < self.shrink_factor < 1:
            raise SensorSpecError(f"FSRSensor.shrink_factor must be in (0, 1), got {self.shrink_factor}")
        if self.dead_taxel_rate >= 1:
            raise SensorSpecError(f"FSRSensor.dead_taxel_rate must be < 1, got {self.dead_taxel_rate}")
        # Plain Python numbers: numpy scalars (np.int64, np.float32) would make spec() not JSON-able.
        for name in ("rows", "cols", "adc_bits", "survey_taxels"):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in (*positive, *non_negative, "shrink_factor"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "_unit_grid", unit_taxel_grid(self.rows, self.cols))
        # Chebyshev distance of each taxel centre from the pad centre on the unit pad.
        object.__setattr__(self, "_unit_chebyshev", np.abs(self._unit_grid).max(axis=1))
        # Taxel indices (into the row-major grid) of the survey subset and of the taxels it leaves out,
        # and the permutation that puts the survey's readings followed by the rest back in grid order.
        survey = self._survey_indices()
        rest = np.setdiff1d(np.arange(self.rows * self.cols), survey)
        object.__setattr__(self, "_survey_index", survey)
        object.__setattr__(self, "_rest_index", rest)
        object.__setattr__(self, "_survey_order", np.argsort(np.concatenate([survey, rest])))

    # ------------------------------------------------------------------------------------ spec
    def spec(self) -> dict:
        """JSON-able specification (for dataset metadata and model compatibility checks)."""
        return {"sensor": "FSRSensor", **asdict(self)}

    @classmethod
    def from_spec(cls, spec: dict) -> FSRSensor:
        """The sensor a :meth:`spec` describes. Specs written before settling existed (no ``settle_mm``)
        describe a rigid pad: ``settle_mm=0``.

        Raises:
            SensorSpecError: unknown fields or bad values.
        """
        fields = {k: v for k, v in spec.items() if k != "sensor"}
        fields.setdefault("settle_mm", 0.0)
        try:
            return cls(**fields)
        except TypeError as exc:
            raise SensorSpecError(f"sensor spec has unknown fields: {exc}") from exc

    def taxel_coordinates(self, side_mm: float | None = None) -> np.ndarray:
        """(rows, cols, 2) pad (x, y) coordinates of the taxel centres, mm, for a pad of ``side_mm``."""
        side = self.side_mm if side_mm is None else float(side_mm)
        return (side * self._unit_grid).reshape(self.rows, self.cols, 2)

    # ----------------------------------------------------------------------------------- press
    def measure_gaps(
        self,
        model: ObjectModel,
        positions,
        normals,
        tangents,
        sides_mm,
    ) -> np.ndarray:
        """Raw gaps (N, rows, cols) float32, mm, of pads of the given sides (N,): pad plane to surface
        along -normal, one ray per taxel, no adaptation and no read-out model.

        Negative where the surface pokes through the pad; ``range_mm`` where the ray misses or the
        surface lies further than the range.

        Raises:
            SensorSpecError: as :meth:`press`, or sides that are not positive and finite.
        """
        positions, normals, tangents = self._check_poses(model, positions, normals, tangents)
        sides = np.broadcast_to(np.asarray(sides_mm, dtype=np.float64), (len(positions),))
        if not (np.isfinite(sides).all() and (sides > 0).all()):
            raise SensorSpecError(f"{model.name}: pad sides must be positive and finite, got {sides_mm!r}")
        return self._gaps(model, positions, normals, tangents, sides)

    def _gaps(self, model, positions, normals, tangents, sides_mm, taxels=None) -> np.ndarray:
        """:meth:`measure_gaps` on checked poses; with ``taxels`` (T,) indices into the taxel grid,
        only those taxels are cast and the result is (N, T)."""
        global _rays_cast
        grid = self._unit_grid if taxels is None else self._unit_grid[taxels]
        grid = np.concatenate([grid, np.ones((len(grid), 1))], axis=1).astype(np.float32)
        n_probes, n_taxels = len(positions), len(grid)
        out = np.empty((n_probes, n_taxels), dtype=np.float32)
        per_cast = max(1, MAX_RAYS_PER_CAST // n_taxels)
        backface_is_inside = model.is_watertight
        # In the scene's frame, in float64, before anything is rounded to float32 (the rays then do not depend
        # on the object's pose).
        positions = model.to_scene(positions)
        normals, tangents = model.to_scene(normals, directions=True), model.to_scene(tangents, directions=True)
        # normals x tangents, as np.cross computes it, without its set-up cost on small batches.
        binormals = (
            normals[:, [1, 2, 0]] * tangents[:, [2, 0, 1]] - normals[:, [2, 0, 1]] * tangents[:, [1, 2, 0]]
        )
        standoff = np.float32(self.standoff_mm)
        for lo in range(0, n_probes, per_cast):
            sl = slice(lo, lo + per_cast)
            # Grid rows (x, y, 1) times the frame rows (side * tangent, 0), (side * binormal, 0) and
            # (origin, inward) build whole rays in one matmul: origin x * tangent + y * binormal + origin
            # and direction inward, written contiguously (cheaper than filling the directions apart).
            inward = (-normals[sl]).astype(np.float32)
            frames = np.zeros((len(inward), 3, 6), dtype=np.float32)
            frames[:, 0, :3] = tangents[sl] * sides_mm[sl, None]
            frames[:, 1, :3] = binormals[sl] * sides_mm[sl, None]
            frames[:, 2, :3] = positions[sl] + self.standoff_mm * normals[sl]
            frames[:, 2, 3:] = inward
            rays = np.matmul(grid, frames)
            # Adding the zero terms turns a -0.0 direction component into +0.0: put those back.
            signed_zero = np.flatnonzero((np.signbit(inward) & (inward == 0)).any(axis=1))
            rays[signed_zero, :, 3:] = inward[signed_zero, None, :]
            hits = model.scene.cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)))
            _rays_cast += len(inward) * n_taxels
            gap = hits["t_hit"].numpy().reshape(len(inward), n_taxels)
            gap -= standoff
            if backface_is_inside:
                # Hitting a triangle from behind means the ray started inside the solid: the surface
                # rises above the stand-off, so the pad penetrates by at least that much.
                face = hits["primitive_normals"].numpy().reshape(len(inward), n_taxels, 3)
                facing = np.matmul(face, inward[:, :, None])[..., 0]
                gap[np.isfinite(gap) & (facing > 0)] = -standoff
            # fmin: a miss (t_hit = inf) reads the range.
            np.fmin(gap, np.float32(self.range_mm), out=out[sl])
        return out if taxels is not None else out.reshape(n_probes, self.rows, self.cols)

    def press(
        self,
        model: ObjectModel,
        positions,
        normals,
        tangents,
        *,
        seed: int | np.random.Generator | None = None,
        adaptive: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Press the pad at N probe poses on ``model`` and read it.

        Args:
            positions: (N, 3) pad centres on the surface, mm.
            normals: (N, 3) outward surface normals (normalised here).
            tangents: (N, 3) pad x axes (made orthogonal to the normals here).
            seed: seed or Generator for taxel noise and dead taxels (unused when both are off).
            adaptive: shrink penetrating pads (see :meth:`_shrink`), re-casting only those probes.

        Returns:
            frames (N, rows, cols) float32 (mm in gap mode, pressure in contact mode) and the pad side
            of each frame (N,) float64, mm.

        Raises:
            SensorSpecError: an empty probe list, mismatched or non-finite arrays, a zero normal, a seed that
                is neither None, a non-negative integer nor a Generator.
        """
        seed = check_seed(seed, f"{model.name}: press", SensorSpecError)
        gaps, sides = self._adapted_gaps(model, positions, normals, tangents, adaptive)
        return self._read(gaps, np.random.default_rng(seed)), sides

    def press_contours(self, model: ObjectModel, contours, seeds, *, adaptive: bool = True) -> list[tuple]:
        """:meth:`press` of each contour (anything with (P, 3) ``positions``, ``normals``, ``tangents``) with its
        seed: [(frames (P, rows, cols), sides (P,))]. The pads of all contours are adapted in one pass (the
        adaptation is per probe, so the frames are those of one press per contour, bit for bit); each
        contour's read-out (noise, dead taxels) draws from its own seed.

        Raises:
            SensorSpecError: as :meth:`press`, or a seed count that differs from the contours'.
        """
        seeds = [check_seed(seed, f"{model.name}: press", SensorSpecError) for seed in seeds]
        if len(seeds) != len(contours):
            raise SensorSpecError(f"{model.name}: {len(seeds)} seeds for {len(contours)} contours")
        if not contours:
            return []
        counts = [len(np.atleast_2d(c.positions)) if np.size(c.positions) else 0 for c in contours]
        if min(counts) == 0:
            raise SensorSpecError(f"{model.name}: contour {counts.index(0)} has no probes; give at least one probe")
        try:
            stacked = [np.concatenate([np.atleast_2d(getattr(c, a)) for c in contours])
                       for a in ("positions", "normals", "tangents")]
        except (TypeError, ValueError) as exc:
            raise SensorSpecError(f"{model.name}: the contours' probe poses do not stack into (N, 3): {exc}") from exc
        gaps, sides = self._adapted_gaps(model, *stacked, adaptive)
        self._warn_if_nothing_touched(model, gaps)
        ends = np.cumsum(counts)[:-1]
        return [(self._read(g, np.random.default_rng(seed)), side)
                for g, side, seed in zip(np.split(gaps, ends), np.split(sides, ends), seeds)]

    def _warn_if_nothing_touched(self, model: ObjectModel, gaps: np.ndarray) -> None:
        """Warn when pads met no surface at all (every taxel at the range): the frames say nothing of the object.
        Objects at the trained size never do this (none of 3,000 presses on ten thin SHREC objects); one much
        smaller than the pad (a mesh in metres loaded without rescaling) does it silently otherwise."""
        missed = int((gaps.reshape(len(gaps), -1).min(axis=1) >= self.range_mm).sum())
        if missed:
            log.warning("%s: %d of %d presses touched nothing (every taxel at the %g mm range): the object is %.3g mm "
                        "across, the pad %g mm of %d x %d taxels; rescale it (load_object(..., size_mm=...))",
                        model.name, missed, len(gaps), self.range_mm, model.size, self.side_mm, self.rows, self.cols)

    def reread(self, clean_frames, seed: int | np.random.Generator | None = None) -> np.ndarray:
        """The frames this sensor reads where a noise-free gap-mode sensor of the same grid and range read
        ``clean_frames`` (P, rows, cols), mm: its taxel noise and dead taxels drawn from ``seed``, bit for bit
        what :meth:`press` with that seed gives, without casting a ray (the pads' geometry does not depend on
        the read-out; a gap-mode reading is the range-clipped gap, and clipping twice changes nothing).

        Raises:
            SensorSpecError: this sensor is not in gap mode, the frames are not (P, rows, cols) of this grid,
                not finite or outside [0, range_mm], or a bad seed.
        """
        seed = check_seed(seed, "FSRSensor.reread", SensorSpecError)
        if self.mode != "gap":
            raise SensorSpecError(f"FSRSensor.reread: only a gap-mode sensor re-reads frames, this one is {self.mode!r}")
        frames = np.asarray(clean_frames)
        if frames.ndim != 3 or frames.shape[1:] != (self.rows, self.cols) or not len(frames):
            raise SensorSpecError(f"FSRSensor.reread: frames must be (P, {self.rows}, {self.cols}) with P >= 1, "
                                  f"got shape {frames.shape}")
        if not np.isfinite(frames).all() or frames.min() < 0 or frames.max() > self.range_mm:
            raise SensorSpecError(f"FSRSensor.reread: frames must be finite gaps in [0, {self.range_mm:g}] mm (a "
                                  "noise-free gap-mode reading)")
        return self._read(frames.astype(np.float32, copy=False), np.random.default_rng(seed))

    def _adapted_gaps(self, model, positions, normals, tangents, adaptive: bool) -> tuple[np.ndarray, np.ndarray]:
        """Raw gaps (N, rows, cols) float32 of the pads after settling and shrinking, and their sides (N,)."""
        positions, normals, tangents = self._check_poses(model, positions, normals, tangents)
        poses = (model, positions, normals, tangents)
        steps = np.zeros(len(positions), dtype=np.int64)
        if adaptive and self.survey_taxels and self.survey_taxels < max(self.rows, self.cols):
            # A coarse survey of the full pad picks each probe's pose and side before the one
            # full-resolution cast.
            coarse = self._gaps(*poses, self._ladder(steps), self._survey_index)
            poses, coarse = self._settle(poses, coarse, self._survey_index, steps)
            self._shrink(poses, coarse, steps, self._survey_index)
            # The survey's last cast was at the final pose and side, so its taxels need no second cast.
            rest = self._gaps(*poses, self._ladder(steps), self._rest_index)
            gaps = np.take(np.concatenate([coarse, rest], axis=1), self._survey_order, axis=1)
        else:
            gaps = self._gaps(*poses, self._ladder(steps)).reshape(len(positions), -1)
        if adaptive:
            # Ripples finer than the survey's taxel pitch show only now.
            poses, gaps = self._settle(poses, gaps, None, steps)
            self._shrink(poses, gaps, steps)
        return gaps.reshape(-1, self.rows, self.cols), self._ladder(steps)

    def _settle(self, poses, gaps: np.ndarray, taxels, steps: np.ndarray):
        """Settle the penetrating pads on the surface under them (``gaps`` (N, T) seen on the ``taxels``,
        None: all, on pads of ``_ladder(steps)``); returns the poses and gaps with the settled probes
        replaced.

        Per penetrating probe, the surface heights under the pad (-gap where a ray found the surface
        from outside) get a least-squares plane z = a x + b y + c in pad coordinates (mm); the pad turns
        to that plane's normal and rises to its highest point, lift = max(z - a x - b y). The new pose
        is kept where 0 <= lift <= settle_mm and its re-cast finds nothing poking through.
        """
        model, positions, normals, tangents = poses
        candidates = np.flatnonzero((gaps < -self.penetration_eps_mm).any(axis=1))
        if self.settle_mm <= 0 or not candidates.size:
            return poses, gaps
        sides = self._ladder(steps[candidates])
        unit_xy = self._unit_grid if taxels is None else self._unit_grid[taxels]  # (T, 2) on the unit pad
        g = gaps[candidates].astype(np.float64)
        found = self._surface_found(g)
        weights = found.astype(np.float64)
        # The fit runs on the unit pad, so its conditioning does not depend on the units or the side.
        design = np.concatenate([unit_xy, np.ones((len(unit_xy), 1))], axis=1)  # (T, 3) rows (u, v, 1)
        # Weighted normal equations as two matrix products (BLAS), not einsum over (P, T, 3, 3).
        normal_matrix = (weights @ (design[:, :, None] * design[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)
        rhs = (weights * -g) @ design
        # Three points not on a line make the 3 x 3 system well posed; others keep their pose.
        well_posed = np.linalg.cond(normal_matrix) < 1e8
        coef = np.zeros((len(candidates), 3))
        coef[well_posed] = np.linalg.solve(normal_matrix[well_posed], rhs[well_posed][:, :, None])[..., 0]
        residual = np.where(found, -g - coef[:, :2] @ unit_xy.T, -np.inf)
        slope = coef[:, :2] / sides[:, None]  # mm of height per mm across the pad
        lift = residual.max(axis=1)
        ok = well_posed & (lift >= 0) & (lift <= self.settle_mm)
        if not ok.any():
            return poses, gaps
        candidates, slope, lift, sides = candidates[ok], slope[ok], lift[ok], sides[ok]
        n, t = normals[candidates], tangents[candidates]
        binormals = np.cross(n, t)
        # The plane z = a x + b y has normal (-a, -b, 1) in pad coordinates (x tangent, y binormal, z normal).
        settled_n = n - slope[:, :1] * t - slope[:, 1:] * binormals
        settled_n /= np.linalg.norm(settled_n, axis=1, keepdims=True)
        settled_t = orthonormal_tangents(settled_n, t, np.array([0.0, 0.0, 1.0]))
        settled_p = positions[candidates] + lift[:, None] * n
        settled_g = self._gaps(model, settled_p, settled_n, settled_t, sides, taxels)
        settled_g = settled_g.reshape(len(candidates), -1)
        fits = (settled_g >= -self.penetration_eps_mm).all(axis=1)
        if not fits.any():
            return poses, gaps
        keep = candidates[fits]
        positions, normals, tangents, gaps = positions.copy(), normals.copy(), tangents.copy(), gaps.copy()
        positions[keep], normals[keep], tangents[keep] = settled_p[fits], settled_n[fits], settled_t[fits]
        gaps[keep] = settled_g[fits]
        return (model, positions, normals, tangents), gaps

    def _surface_found(self, gaps: np.ndarray) -> np.ndarray:
        """Where a ray found the surface: not where it started inside the solid (``-standoff_mm``) or found nothing
        (``range_mm``), which give no height. The gaps hold those as float32: compared with the float64 settings, a
        range such as 15.81 mm would count a miss (its float32 just below) as surface at the far end of the range,
        and a stand-off such as 5.1 mm an inside start as surface."""
        return (gaps > -np.float32(self.standoff_mm)) & (gaps < np.float32(self.range_mm))

    def _survey_indices(self) -> np.ndarray:
        """Row-major taxel indices of a survey_taxels x survey_taxels subset of the taxel grid, outermost
        rows and columns included, so that a side passing the survey fails the full cast only through the
        taxels in between."""
        rows = np.round(np.linspace(0, self.rows - 1, min(self.survey_taxels, self.rows))).astype(np.int64)
        cols = np.round(np.linspace(0, self.cols - 1, min(self.survey_taxels, self.cols))).astype(np.int64)
        return (rows[:, None] * self.cols + cols[None, :]).ravel()

    def _ladder(self, steps: np.ndarray) -> np.ndarray:
        """Pad sides side_mm * shrink_factor**steps, never below min_side_mm."""
        return np.maximum(self.side_mm * self.shrink_factor ** steps.astype(np.float64), self.min_side_mm)

    def _next_steps(self, gaps: np.ndarray, taxels, steps: np.ndarray) -> np.ndarray:
        """Ladder steps after seeing ``gaps`` (N, T) of the ``taxels`` (None: all) on pads of
        ``_ladder(steps)``.

        A penetrating taxel (gap < -eps) at Chebyshev distance c from the pad centre is inside every pad
        of side > 2c (the gap at a point of the pad plane does not depend on the pad side), so the pad
        jumps to the first ladder side <= 2c of the nearest such taxel, at least one step down.
        """
        sides = self._ladder(steps)
        unit_chebyshev = self._unit_chebyshev if taxels is None else self._unit_chebyshev[taxels]
        penetrating = gaps < -self.penetration_eps_mm
        some = np.flatnonzero(penetrating.any(axis=1))  # usually few pads: look only at those
        nearest = np.full(len(steps), np.inf)
        # side * min(c) == min(side * c): rounding is monotonic, so this is the nearest taxel's distance.
        nearest[some] = sides[some] * np.where(penetrating[some], unit_chebyshev, np.inf).min(axis=1)
        hit = np.isfinite(nearest) & (sides > self.min_side_mm)
        # Past the step that reaches min_side_mm further steps change nothing: cap there.
        last = max(int(np.ceil(np.log(self.min_side_mm / self.side_mm) / np.log(self.shrink_factor))), 0)
        # A taxel at the very centre (nearest = 0) penetrates every pad: straight to the last step.
        ratio = np.maximum(2 * nearest[hit] / self.side_mm, 1e-300)
        needed = np.minimum(np.ceil(np.log(ratio) / np.log(self.shrink_factor)), last).astype(np.int64)
        new = steps.copy()
        new[hit] = np.minimum(np.maximum(needed, steps[hit] + 1), last)
        return new

    def _shrink(self, poses, gaps: np.ndarray, steps: np.ndarray, taxels=None) -> None:
        """Shrink penetrating pads in place (``gaps`` (N, T) seen on the ``taxels``, None: all, and
        ``steps``), re-casting only them on the same taxels.

        Every round moves each still-penetrating pad at least one ladder step down until it reaches
        min_side_mm, so the loop ends after at most log(min_side / side) / log(shrink_factor) + 1 rounds.
        """
        model, positions, normals, tangents = poses
        rounds = 0
        while True:
            new = self._next_steps(gaps, taxels, steps)
            active = np.flatnonzero(new != steps)
            if not active.size:
                break
            steps[active] = new[active]
            gaps[active] = self._gaps(
                model,
                positions[active],
                normals[active],
                tangents[active],
                self._ladder(steps[active]),
                taxels,
            ).reshape(len(active), -1)
            rounds += 1
        if rounds:
            log.debug(
                "%s: adaptive pad took %d re-cast rounds on %d taxels", model.name, rounds, gaps.shape[1]
            )

    def _read(self, gaps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Turn raw gaps into readings: range clip or contact pressure, noise, ADC, dead taxels."""
        dead = rng.random((self.rows, self.cols)) < self.dead_taxel_rate if self.dead_taxel_rate > 0 else None
        if self.mode == "gap":
            frames = np.clip(gaps, 0.0, self.range_mm)
            if self.noise_std > 0:
                frames = np.clip(frames + rng.normal(0.0, self.noise_std, frames.shape), 0.0, self.range_mm)
            if dead is not None:
                frames[:, dead] = self.range_mm
            return frames.astype(np.float32, copy=False)
        pressure = self.stiffness * np.maximum(0.0, self.indent_mm - gaps.astype(np.float64))
        # A gap at the range means nothing within it (a miss): no contact, even where indent_mm > range_mm.
        pressure[gaps >= np.float32(self.range_mm)] = 0.0
        if self.noise_std > 0:
            pressure = pressure + rng.normal(0.0, self.noise_std, pressure.shape)
        pressure = np.clip(pressure, 0.0, self.saturation)
        levels = 2**self.adc_bits - 1
        # Divide first: pressure / saturation is in [0, 1], so no product overflows.
        pressure = np.round(pressure / self.saturation * levels) * (self.saturation / levels)
        if dead is not None:
            pressure[:, dead] = 0.0
        return pressure.astype(np.float32)

    def _check_poses(self, model, positions, normals, tangents):
        arrays = []
        for name, value in (("positions", positions), ("normals", normals), ("tangents", tangents)):
            try:
                array = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise SensorSpecError(f"{model.name}: probe {name} are not numeric: {exc}") from exc
            if array.size == 0:
                raise SensorSpecError(
                    f"{model.name}: empty probe list ({name} has no rows); give at least one probe"
                )
            if array.ndim == 1 and array.shape == (3,):
                array = array[None, :]
            if array.ndim != 2 or array.shape[1] != 3:
                raise SensorSpecError(f"{model.name}: probe {name} must be (N, 3), got shape {array.shape}")
            if not np.isfinite(array).all():
                raise SensorSpecError(f"{model.name}: probe {name} contain NaN or Inf")
            arrays.append(array)
        positions, normals, tangents = arrays
        if not len(positions) == len(normals) == len(tangents):
            raise SensorSpecError(
                f"{model.name}: {len(positions)} positions, {len(normals)} normals and {len(tangents)} tangents differ"
            )
        if (np.abs(positions) > MAX_COORDINATE_MM).any():
            raise SensorSpecError(f"{model.name}: probe positions lie beyond +-{MAX_COORDINATE_MM:g} mm of the origin")
        # Rows whose squares would overflow (a norm of inf made them zero, every ray a miss) are scaled down first;
        # the others are left as they are, bit for bit.
        normals, tangents = _tame(normals), _tame(tangents)
        length = np.linalg.norm(normals, axis=1)
        if (length < 1e-12).any():
            raise SensorSpecError(f"{model.name}: probe {int(np.argmin(length))} has a zero normal")
        normals = normals / length[:, None]
        tangents = orthonormal_tangents(normals, tangents, np.array([0.0, 0.0, 1.0]))
        return positions, normals, tangents


def _tame(vectors: np.ndarray) -> np.ndarray:
    """``vectors`` (N, 3) with the rows above 1e150 in some component divided by that component's magnitude."""
    largest = np.abs(vectors).max(axis=1)
    huge = largest > 1e150
    if not huge.any():
        return vectors
    vectors = vectors.copy()
    vectors[huge] /= largest[huge, None]
    return vectors


__all__ = ["MAX_RAYS_PER_CAST", "MODES", "FSRSensor", "rays_cast", "unit_taxel_grid"]
