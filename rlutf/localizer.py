"""The RLuTF localizer: the paper's Algorithm 1, its open points resolved, and a refinement.

One :class:`Localizer` tracks one robot on one map. Each :meth:`Localizer.update` takes the
odometry motion since the previous scan and the new scan, and

1. predicts ``Ov_new = Or_old (+) motion``;
2. casts the scan's own beams (those with a return) from the prediction: the virtual polygon
   ``Pv``, compared with the real polygon ``Pr`` by the configured discrepancy;
3. accepts the prediction if the discrepancy is under ``epsilon``; otherwise samples
   ``candidates`` random poses within ``delta`` (position) and ``delta_theta`` (heading) of the
   current best, keeps the best (the current best too, unless ``mode == "paper"``), halves the
   radii and repeats until ``epsilon`` is met, the radii fall under ``delta_min`` (and, in the
   default mode, ``delta_theta_min``), or ``max_rounds`` rounds were used;
4. (``refine``) refines the result by robust least squares on the ranges, which also gives the
   pose's covariance (:mod:`rlutf.refine`);
5. reports ``lost`` when too few beams fit the map at the pose returned (``min_fit`` of them
   within ``fit_distance``), whatever the discrepancy's unit.

In the default mode the first radii follow the odometry motion and the previous correction, and
a search that ends at the edge of its radii, or with a discrepancy well over the recent typical
one, is followed by another around its best with doubled radii (the full radii when over
``lost_threshold``). The area discrepancy caps each beam's share at ``area_cap`` or the round's
position radius, whichever is larger, so that early rounds still see beams that are far off.

A pose given with a wide uncertainty (the initial pose, a reset, the update after a ``lost``
one, or a prediction that does not fit) is searched first over a grid of poses scored with the
map's distance field (:mod:`rlutf.field`, ``wide_search``); the best few are refined and the
best fit is kept.

Randomness comes from a seeded :class:`numpy.random.Generator` owned by the localizer, so the
same seed and inputs give the same poses bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf import _kernels
from rlutf.discrepancy import PolarArea, anchored_turning, turning_steps
from rlutf.errors import ConfigError
from rlutf.field import WideSearch, wide_search
from rlutf.map import Map
from rlutf.motion import compose, wrap_scalar
from rlutf.raycast import Beams
from rlutf.refine import Refinement, RefineSettings, refine_pose
from rlutf.scan import Scan, beam_points, simplify_ring
from rlutf.search import RandomSearch

FloatArray = NDArray[np.float64]

Mode = Literal["default", "paper"]
DiscrepancyKind = Literal["turning", "area", "combined"]
Status = Literal["tracking", "corrected", "lost"]

#: ``(epsilon, lost_threshold)`` of each discrepancy in its own unit, for the default mode.
#: Measured on the simulated scenarios at the true pose and at poses 2, 5, 10 and 30 cm off:
#: the capped area (metres) is 0.002 at the truth, 0.012 at 5 cm (where the refinement's basin
#: still holds) and saturates near 0.03; the anchored turning distance (radians) is 0.2 at the
#: truth with a long tail (0.8 at the 90th percentile), 0.7 at 2 cm and 1.2 to 1.6 beyond.
THRESHOLDS: dict[str, tuple[float, float]] = {
    "area": (0.012, 0.03),
    "turning": (0.3, 1.2),
    "combined": (0.35, 1.5),
}
#: ``epsilon`` of the default mode without ``refine``: the search must then reach the bottom of
#: the basin itself, so it accepts only a near-noise-free fit (version 0.1's default).
SEARCH_ONLY_EPSILON: dict[str, float] = {"area": 0.0015, "turning": 0.3, "combined": 0.35}
#: The same for ``mode="paper"`` (perimeter-normalised turning functions, exact area): the
#: exact area is 0.002 at the truth and 0.03 at 2 cm; the normalised turning distance 0.19 and
#: 0.84.
PAPER_THRESHOLDS: dict[str, tuple[float, float]] = {
    "area": (0.005, 0.1),
    "turning": (0.25, 1.0),
    "combined": (0.3, 1.3),
}


@dataclass(frozen=True)
class LocalizerConfig:
    """Every parameter of the localizer, with its unit.

    Attributes:
        mode: ``"default"`` or ``"paper"`` (Algorithm 1 read literally: perimeter-normalised
            turning functions, no elitism, fixed initial radius, exact area, no refinement).
        discrepancy: ``"turning"`` (anchored turning function, radians), ``"area"`` (area between
            the polygons over the perimeter, metres) or ``"combined"`` (turning plus
            ``area_weight`` times area).
        epsilon: accept a pose whose discrepancy is under this (the discrepancy's unit);
            ``None``: the discrepancy's own default (:data:`THRESHOLDS`; without ``refine``,
            :data:`SEARCH_ONLY_EPSILON`).
        lost_threshold: a search stage ending over this searches again with the full radii
            (the discrepancy's unit); ``None``: the discrepancy's own default.
        candidates: random candidates per search round (the paper uses 3).
        delta: initial search radius in position, metres.
        delta_theta: initial search radius in heading, radians.
        delta_min: the search stops when the position radius falls under this, metres.
        delta_theta_min: ... and (default mode) the heading radius under this, radians.
        max_rounds: most search rounds per update.
        adaptive: start the search with radii from the odometry motion and the previous
            correction (default mode only), and search again with larger radii when a stage ends
            over ``lost_threshold`` (the full radii) or at the edge of its radii (doubled).
        delta_start: smallest adaptive position radius, metres.
        delta_per_metre: adaptive position radius per metre travelled.
        delta_theta_start: smallest adaptive heading radius, radians.
        delta_theta_per_radian: adaptive heading radius per radian turned.
        delta_theta_per_metre: adaptive heading radius per metre travelled, radians.
        delta_per_correction: adaptive radii grow by this times the previous update's correction
            (position and heading).
        expand_fraction: (adaptive) when a stage's best pose moved more than this fraction of its
            position or heading radius, another stage searches around it with the radii doubled.
        surprise_ratio: (adaptive) a stage that ends over this many times the running typical
            discrepancy (or over ``lost_threshold``) is followed by one with the full radii.
        typical_rate: weight of each update's discrepancy in the running typical one.
        max_stages: (adaptive) most search stages per update.
        area_cap: with ``discrepancy="area"``, each beam's share of the area is capped at a band
            of this width, metres (see :class:`rlutf.discrepancy.PolarArea`), or of the round's
            position radius times ``cap_per_radius`` if wider; ``None`` uses the exact area.
            ``"combined"`` always uses the exact area.
        cap_per_radius: (default mode) the cap is at least this times the round's position
            radius, so that the early, wide rounds of a search see beams that are far off.
        simplify_tolerance: Douglas-Peucker tolerance for the real polygon, metres (about two
            to three times the range noise).
        area_weight: weight of the area term in ``"combined"``, radians per metre.
        max_gap: widest angular gap between returns bridged by a polygon edge, radians; past
            it the polygon closes through the sensor.
        min_returns: fewer returns than this give status ``lost`` without a comparison.
        refine: refine the search's result by robust least squares on the ranges
            (:mod:`rlutf.refine`).
        refine_iterations: most casts of the scan per refinement.
        refine_tolerance: the refinement stops on a step under this, metres and radians.
        noise_min: smallest range noise the refinement assumes, metres.
        noise_max: largest range noise the refinement assumes, metres.
        max_incidence: the refinement leaves out beams hitting a wall more obliquely than this,
            radians from the wall's normal.
        fit_distance: a beam fits the map when its measured range is within this of the range
            cast from the pose, metres.
        min_fit: status ``lost`` when fewer than this share of the returns fit.
        wide_search: search a wide region on the distance field when the pose is uncertain:
            the first update, after :meth:`Localizer.reset`, after a ``lost`` update, and when
            the prediction does not fit (default mode only).
        spread: how far off (metres) a pose given without its own spread may be: an
            operator's click on a map.
        spread_heading: the same for the heading, radians.
        wide_step: position step of the wide search's grid, metres.
        wide_cap: the wide search's per-point cap, metres.
        wide_keep: poses of the wide search refined and compared.
        select_scale: scale of the Cauchy cost that compares refined candidates, metres (about
            three times a good scanner's range noise: fine enough to tell two nearby basins
            apart, coarse enough that map errors do not decide).
        seed: base seed of the random generator.
    """

    mode: Mode = "default"
    discrepancy: DiscrepancyKind = "area"
    epsilon: float | None = None
    lost_threshold: float | None = None
    candidates: int = 8
    delta: float = 0.3
    delta_theta: float = 0.12
    delta_min: float = 0.003
    delta_theta_min: float = 0.001
    max_rounds: int = 10
    adaptive: bool = True
    delta_start: float = 0.004
    delta_per_metre: float = 0.05
    delta_theta_start: float = 0.002
    delta_theta_per_radian: float = 0.05
    delta_theta_per_metre: float = 0.02
    delta_per_correction: float = 1.0
    expand_fraction: float = 0.75
    surprise_ratio: float = 1.6
    typical_rate: float = 0.1
    max_stages: int = 4
    area_cap: float | None = 0.1
    cap_per_radius: float = 1.0
    simplify_tolerance: float = 0.03
    area_weight: float = 5.0
    max_gap: float = 0.35
    min_returns: int = 8
    refine: bool = True
    refine_iterations: int = 12
    refine_tolerance: float = 1e-4
    noise_min: float = 0.002
    noise_max: float = 0.2
    max_incidence: float = math.radians(80.0)
    fit_distance: float = 0.1
    min_fit: float = 0.5
    wide_search: bool = True
    spread: float = 0.5
    spread_heading: float = math.radians(15.0)
    wide_step: float = 0.1
    wide_cap: float = 0.3
    wide_keep: int = 6
    select_scale: float = 0.03
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in ("default", "paper"):
            raise ConfigError(f"mode: expected 'default' or 'paper', got {self.mode!r}")
        if self.discrepancy not in ("turning", "area", "combined"):
            raise ConfigError(f"discrepancy: unknown kind {self.discrepancy!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"{f.name}: must be finite, got {value}")
        positive = (
            "delta",
            "delta_theta",
            "delta_min",
            "max_gap",
            "refine_tolerance",
            "noise_min",
            "noise_max",
            "max_incidence",
            "fit_distance",
            "spread",
            "spread_heading",
            "wide_step",
            "wide_cap",
            "select_scale",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: must be positive, got {getattr(self, name)}")
        for name in ("epsilon", "lost_threshold"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ConfigError(f"{name}: must be positive or None, got {value}")
        non_negative = (
            "delta_theta_min",
            "delta_theta_per_metre",
            "expand_fraction",
            "surprise_ratio",
            "typical_rate",
            "delta_start",
            "delta_per_metre",
            "delta_theta_start",
            "delta_theta_per_radian",
            "delta_per_correction",
            "simplify_tolerance",
            "cap_per_radius",
        )
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if self.area_cap is not None and not self.area_cap > 0:
            raise ConfigError(f"area_cap: must be positive or None, got {self.area_cap}")
        if self.candidates < 1:
            raise ConfigError(f"candidates: must be at least 1, got {self.candidates}")
        if self.max_rounds < 0:
            raise ConfigError(f"max_rounds: must be at least 0, got {self.max_rounds}")
        if self.max_stages < 1:
            raise ConfigError(f"max_stages: must be at least 1, got {self.max_stages}")
        if self.refine_iterations < 1:
            raise ConfigError(
                f"refine_iterations: must be at least 1, got {self.refine_iterations}"
            )
        if self.wide_keep < 1:
            raise ConfigError(f"wide_keep: must be at least 1, got {self.wide_keep}")
        if not 0.0 <= self.min_fit <= 1.0:
            raise ConfigError(f"min_fit: must be within [0, 1], got {self.min_fit}")
        if self.noise_max < self.noise_min:
            raise ConfigError("noise_max: must be at least noise_min")
        if self.max_incidence >= math.pi / 2:
            raise ConfigError(f"max_incidence: must be under pi/2, got {self.max_incidence}")
        if self.lost_above < self.accept_below:
            raise ConfigError("lost_threshold: must be at least epsilon")

    @property
    def accept_below(self) -> float:
        """``epsilon``, or the discrepancy's own default."""
        if self.epsilon is not None:
            return self.epsilon
        if self.mode == "paper":
            return PAPER_THRESHOLDS[self.discrepancy][0]
        if not self.refine:
            return SEARCH_ONLY_EPSILON[self.discrepancy]
        return THRESHOLDS[self.discrepancy][0]

    @property
    def lost_above(self) -> float:
        """``lost_threshold``, or the discrepancy's own default."""
        table = PAPER_THRESHOLDS if self.mode == "paper" else THRESHOLDS
        return (
            self.lost_threshold if self.lost_threshold is not None else table[self.discrepancy][1]
        )

    @classmethod
    def paper(cls, **overrides: object) -> LocalizerConfig:
        """The paper's Algorithm 1 as literally as it can be read: step 4 compares the two
        polygons' turning functions (perimeter-normalised, the area between them), three random
        candidates per round, no elitism, no refinement."""
        base = cls(
            mode="paper",
            discrepancy="turning",
            adaptive=False,
            candidates=3,
            delta=0.04,
            delta_theta=0.03,
            delta_min=0.001,
            max_rounds=12,
            area_cap=None,
            refine=False,
            wide_search=False,
        )
        return replace(base, **overrides)  # type: ignore[arg-type]

    @classmethod
    def paper_area(cls, **overrides: object) -> LocalizerConfig:
        """:meth:`paper` with the area between the two polygons as its comparison (the paper
        preset of version 0.1)."""
        return cls.paper(discrepancy="area", **overrides)

    def refine_settings(self) -> RefineSettings:
        """The refinement's parameters."""
        return RefineSettings(
            iterations=self.refine_iterations,
            tolerance=self.refine_tolerance,
            sigma_min=self.noise_min,
            sigma_max=self.noise_max,
            max_incidence=self.max_incidence,
        )


@dataclass(frozen=True)
class LocalizeResult:
    """Outcome of one update.

    Attributes:
        pose: ``(3,)`` the corrected pose ``(x, y, theta)`` in the map frame.
        discrepancy: the discrepancy at ``pose``; ``inf`` when no comparison was possible.
        iterations: search rounds used (0 when the prediction was accepted).
        status: ``tracking``, ``corrected`` or ``lost``.
        evaluations: candidate poses scored, the prediction included.
        covariance: ``(3, 3)`` covariance of ``pose`` (m^2, m rad, rad^2), or ``None``.
        fit: share of the scan's returns within ``fit_distance`` of the map at ``pose``.
        sigma: the range noise estimated from the scan at ``pose``, metres (NaN if none).
        refine_casts: casts of the scan made by the refinement.
    """

    pose: FloatArray
    discrepancy: float
    iterations: int
    status: Status
    evaluations: int
    covariance: FloatArray | None = None
    fit: float = math.nan
    sigma: float = math.nan
    refine_casts: int = 0

    @property
    def inliers(self) -> float:
        """The same as :attr:`fit`."""
        return self.fit


class _Problem:
    """What one update compares against: the real scan, its polygon and the beams to cast."""

    def __init__(self, world: Map, scan: Scan, config: LocalizerConfig, beams: Beams) -> None:
        self.world = world
        self.config = config
        self.offset = np.ascontiguousarray(scan.sensor_offset, dtype=np.float64)
        self.scan_range = scan.range_max
        self.range_max = scan.range_max
        keep, self.closing, weights = _kernels.scan_terms(
            scan.ranges,
            beams.angles,
            beams.cos,
            beams.sin,
            scan.range_min,
            scan.range_max,
            scan.covers_full_circle(),
            config.max_gap,
        )
        self.count = len(keep)
        if self.count < config.min_returns:
            return
        self.beams = beams.take(keep)
        self.real_ranges = scan.ranges[keep]
        kind = config.discrepancy
        self.cap = config.area_cap if kind == "area" else None
        if kind != "turning":
            # The combined discrepancy keeps the exact area: capped, its turning term (which
            # people and grazed edges disturb the most) would dominate.
            self.area = PolarArea.of_terms(self.real_ranges, weights, self.cap)
        if self.cap is not None:
            # A virtual range past the real one plus the cap counts as the cap, so no beam needs
            # casting farther than the longest return plus the widest cap of a search.
            widest = max(self.cap, config.cap_per_radius * 2.0 * config.delta)
            longest = float(self.real_ranges.max()) + widest
            self.range_max = min(self.range_max, longest)
        if kind != "area":
            points = beam_points(self.real_ranges, self.beams.cos, self.beams.sin, self.offset)
            real = np.vstack([points, self.offset[None, :2]]) if self.closing else points
            self.real_steps = turning_steps(simplify_ring(real, config.simplify_tolerance))

    def area_terms(self) -> tuple[FloatArray, FloatArray, FloatArray, float] | None:
        """The capped polar area's terms for :func:`rlutf.refine.refine_pose`, if the
        discrepancy is the capped area."""
        if self.cap is None:
            return None
        area = self.area
        return (area.weights, area.real_sq, area.band(self.cap), self.range_max)

    def points(self) -> FloatArray:
        """``(n, 2)`` the scan's returns in the base frame."""
        return beam_points(self.real_ranges, self.beams.cos, self.beams.sin, self.offset)

    def score(self, poses: FloatArray, cap: float | None = None) -> FloatArray:
        """``(K,)`` discrepancies of ``(K, 3)`` poses; ``inf`` outside the free space.

        ``cap`` replaces the configured area cap (capped area only)."""
        inside = self.world.contains(poses[:, :2])
        out = np.full(len(poses), np.inf)
        if inside.any():
            out[inside] = self._discrepancy(np.ascontiguousarray(poses[inside]), cap)
        return out

    def _discrepancy(self, poses: FloatArray, cap: float | None) -> FloatArray:
        kind = self.config.discrepancy
        if kind == "area":
            area = self.area
            caps = area.band(cap if cap is not None else self.cap)
            return _kernels.score_area(
                poses,
                self.offset,
                self.beams.cos,
                self.beams.sin,
                area.real_sq,
                area.weights,
                caps,
                self.range_max,
                *self.world.grid,
            )
        sensors = np.ascontiguousarray(compose(poses, self.offset))
        ranges, _ = _kernels.cast_poses(
            sensors, self.beams.cos, self.beams.sin, self.range_max, True, *self.world.grid
        )
        np.minimum(ranges, self.range_max, out=ranges)
        return self.of_ranges(ranges)

    def of_ranges(self, ranges: FloatArray, cap: float | None = None) -> FloatArray:
        """``(K,)`` discrepancies of ``(K, n)`` virtual ranges (``inf`` past the range)."""
        r = np.minimum(ranges, self.range_max)
        kind = self.config.discrepancy
        if kind == "area":
            return self.area(r, cap if cap is not None else self.cap)
        rings = beam_points(r, self.beams.cos, self.beams.sin, self.offset)
        if self.closing:
            origin = np.broadcast_to(self.offset[:2], (len(r), 1, 2))
            rings = np.concatenate([rings, origin], axis=1)
        d = anchored_turning(
            turning_steps(rings), self.real_steps, normalise=self.config.mode == "paper"
        )
        if kind == "combined":
            d = d + self.config.area_weight * self.area(r)
        return d


class Localizer:
    """Tracks one robot's pose on a map with RLuTF.

    Args:
        world: the map.
        pose: ``(3,)`` initial pose of the robot base in the map frame.
        config: parameters; defaults to :class:`LocalizerConfig`.
        seed: seed of this localizer's generator (e.g. derived from the robot id); combined
            with ``config.seed``.
        spread: ``(metres, radians)``: how far off ``pose`` may be; the first update searches
            that wide (``wide_search``). ``None``: the config's ``spread`` and
            ``spread_heading``.
    """

    def __init__(
        self,
        world: Map,
        pose: ArrayLike,
        config: LocalizerConfig | None = None,
        seed: int = 0,
        spread: tuple[float, float] | None = None,
    ) -> None:
        self.config = config or LocalizerConfig()
        self._map = world
        self._pose = _pose3(pose)
        self._rng = np.random.default_rng([int(self.config.seed), int(seed)])
        self._beams: tuple[tuple[int, float, float], Beams] | None = None
        # Size of the last correction (position, heading): scales the next search.
        self._correction = (0.0, 0.0)
        # Running typical discrepancy at the corrected pose: a much larger one is a surprise.
        self._typical = math.inf
        self._previous: _Problem | None = None
        self._spread: tuple[float, float] | None = self._spread_of(spread)
        self._refine_settings = self.config.refine_settings()

    @property
    def pose(self) -> FloatArray:
        """``(3,)`` current pose estimate (a copy)."""
        return self._pose.copy()

    @property
    def map(self) -> Map:
        """The map the robot is on."""
        return self._map

    def reset(self, pose: ArrayLike, spread: tuple[float, float] | None = None) -> None:
        """Re-seed the pose (an operator's initial pose); the next update searches ``spread``
        around it (``None``: the config's ``spread`` and ``spread_heading``)."""
        self._pose = _pose3(pose)
        self._correction = (0.0, 0.0)
        self._typical = math.inf
        self._spread = self._spread_of(spread)

    def set_map(self, world: Map) -> None:
        """Switch to a new version of the map, keeping the pose."""
        self._map = world

    def _spread_of(self, spread: tuple[float, float] | None) -> tuple[float, float]:
        cfg = self.config
        if spread is None:
            return (cfg.spread, cfg.spread_heading)
        r, h = float(spread[0]), float(spread[1])
        if not (math.isfinite(r) and math.isfinite(h) and r >= 0 and h >= 0):
            raise ValueError(f"spread: expected two finite numbers >= 0, got {spread}")
        return (r, h)

    def update(self, motion: ArrayLike, scan: Scan) -> LocalizeResult:
        """One RLuTF step: predict with ``motion``, correct with ``scan``.

        Args:
            motion: ``(3,)`` odometry motion since the previous update, in the robot frame.
            scan: the new scan.

        Returns:
            The result; the localizer's pose becomes ``result.pose``.
        """
        cfg = self.config
        mot = _pose3(motion)
        predicted = _compose(self._pose, mot)
        problem = _Problem(self._map, scan, cfg, self._scan_beams(scan))
        if problem.count < cfg.min_returns:
            inside = bool(self._map.contains(predicted[None, :2])[0])
            self._pose = predicted if inside else self._pose
            return LocalizeResult(self._pose.copy(), math.inf, 0, "lost", 0)

        wide = cfg.wide_search and cfg.mode != "paper"
        spread, self._spread = self._spread, None
        if wide and spread is not None and spread[0] + spread[1] > 0:
            best, rounds, evaluations, fit = self._wide(problem, predicted, spread)
        else:
            gate = cfg.refine and problem.cap is not None and cfg.mode != "paper"
            fit = self._fit(problem, predicted, gate=gate)
            if gate and not fit.gated:
                # Algorithm 1's step 4: the prediction fits; the refinement started from it.
                best, rounds, evaluations = predicted, 0, 1
            else:
                best, rounds, evaluations = self._rlutf(
                    problem, predicted, mot, fit.area_start if gate else None
                )
                fit = self._fit(problem, best)
            if wide and fit.fit < cfg.min_fit:
                # The prediction's basin does not fit the scan: odometry slipped or jumped.
                # Look wider before calling the robot lost.
                other, r2, e2, other_fit = self._wide(
                    problem, predicted, (cfg.spread, cfg.spread_heading)
                )
                evaluations += e2
                if _better(other_fit, fit, cfg.select_scale):
                    best, fit, rounds = other, other_fit, rounds + r2
        pose = fit.pose if cfg.refine else best
        share = fit.fit
        discrepancy = (
            fit.area_final
            if problem.cap is not None
            else float(problem.of_ranges(fit.ranges[None])[0])
        )
        if not math.isfinite(discrepancy):
            discrepancy = math.inf
        elif discrepancy <= cfg.lost_above:
            rate = cfg.typical_rate
            self._typical = (
                discrepancy
                if not math.isfinite(self._typical)
                else ((1.0 - rate) * self._typical + rate * discrepancy)
            )
        self._correction = (
            math.hypot(float(pose[0] - predicted[0]), float(pose[1] - predicted[1])),
            abs(wrap_scalar(float(pose[2] - predicted[2]))),
        )
        if share < cfg.min_fit:
            status: Status = "lost"
            # Look wider at the next scan (default mode): a lost robot comes back by itself.
            self._spread = (cfg.spread, cfg.spread_heading) if wide else None
        elif rounds == 0:
            status = "tracking"
        else:
            status = "corrected"
        self._pose = np.array([pose[0], pose[1], wrap_scalar(float(pose[2]))])
        # Free the previous update's arrays only now that this one has made its own: freed
        # first, they would leave free memory at the top of the heap, which malloc gives back to
        # the system, and every update would pay page faults to map it again.
        self._previous = problem
        return LocalizeResult(
            self._pose.copy(),
            discrepancy,
            rounds,
            status,
            evaluations,
            fit.covariance,
            share,
            fit.sigma,
            fit.casts if cfg.refine else 0,
        )

    def _fit(self, problem: _Problem, pose: FloatArray, gate: bool = False) -> Refinement:
        """The refinement from ``pose`` (or, without ``refine``, ``pose`` evaluated); with
        ``gate``, only if the polar area at ``pose`` is under ``epsilon``."""
        cfg = self.config
        return refine_pose(
            self._map,
            pose,
            problem.beams,
            problem.real_ranges,
            problem.offset,
            problem.scan_range,
            self._refine_settings,
            fit_distance=cfg.fit_distance,
            iterations=None if cfg.refine else 1,
            area=problem.area_terms(),
            accept_below=cfg.accept_below if gate else 0.0,
        )

    def _rlutf(
        self,
        problem: _Problem,
        predicted: FloatArray,
        mot: FloatArray,
        scored: float | None = None,
    ) -> tuple[FloatArray, int, int]:
        """Algorithm 1's comparison and random search: ``(best pose, rounds, evaluations)``;
        ``scored`` is the prediction's discrepancy if known."""
        cfg = self.config
        best = predicted
        best_d = float(problem.score(predicted[None])[0]) if scored is None else scored
        evaluations = 1
        rounds = 0
        if best_d < cfg.accept_below:
            return best, rounds, evaluations
        delta, delta_theta = self._initial_radii(mot)
        for _stage in range(max(cfg.max_stages, 1)):
            start = best
            search = self._search(start, delta, delta_theta)
            search.best_d = best_d
            score = self._scorer(problem, search)
            evaluations += search.run(score)
            best, best_d = search.best, search.best_d
            if not math.isfinite(best_d):
                break
            rounds += search.rounds
            radii = self._next_radii(start, best, best_d, delta, delta_theta)
            if radii is None:
                break
            delta, delta_theta = radii
        return best, rounds, evaluations

    def _scorer(self, problem: _Problem, search: RandomSearch) -> _Scorer:
        cfg = self.config
        if problem.cap is None or cfg.mode == "paper" or cfg.cap_per_radius == 0:
            return _Scorer(problem, search, None)
        return _Scorer(problem, search, (problem.cap, cfg.cap_per_radius))

    def _wide(
        self, problem: _Problem, predicted: FloatArray, spread: tuple[float, float]
    ) -> tuple[FloatArray, int, int, Refinement]:
        """The wide search around ``predicted``: grid on the distance field, the best few
        refined, the best fit kept. Returns ``(pose, rounds, evaluations, its fit)``."""
        cfg = self.config
        settings = WideSearch(step=cfg.wide_step, cap=cfg.wide_cap, keep=cfg.wide_keep)
        found, scored = wide_search(
            self._map, predicted, problem.points(), spread[0], spread[1], settings
        )
        starts = [predicted, *(pose for pose, _ in found)]
        best_fit: Refinement | None = None
        best = predicted
        for start in starts:
            fit = self._fit(problem, start)
            if best_fit is None or _better(fit, best_fit, cfg.select_scale):
                best_fit, best = fit, (fit.pose if cfg.refine else start)
        assert best_fit is not None
        return best, 1, scored + len(starts), best_fit

    def _scan_beams(self, scan: Scan) -> Beams:
        """Beams of the scan's geometry, prepared once per geometry."""
        key = (len(scan.ranges), scan.angle_min, scan.angle_increment)
        if self._beams is None or self._beams[0] != key:
            self._beams = (key, Beams.of(scan.angles))
        return self._beams[1]

    def _search(self, start: FloatArray, delta: float, delta_theta: float) -> RandomSearch:
        cfg = self.config
        paper = cfg.mode == "paper"
        return RandomSearch(
            self._rng,
            start,
            delta,
            delta_theta,
            candidates=cfg.candidates,
            max_rounds=cfg.max_rounds,
            delta_min=cfg.delta_min,
            # The paper halves one radius; the default mode also waits for the heading radius.
            delta_theta_min=math.inf if paper else cfg.delta_theta_min,
            epsilon=cfg.accept_below,
            elitist=not paper,
        )

    def _initial_radii(self, mot: FloatArray) -> tuple[float, float]:
        """Search radii (position, heading) of the first stage."""
        cfg = self.config
        if not cfg.adaptive or cfg.mode == "paper":
            return cfg.delta, cfg.delta_theta
        travel = math.hypot(float(mot[0]), float(mot[1]))
        turn = abs(float(mot[2]))
        moved, turned = self._correction
        delta = cfg.delta_start + cfg.delta_per_metre * travel + cfg.delta_per_correction * moved
        delta_theta = (
            cfg.delta_theta_start
            + cfg.delta_theta_per_radian * turn
            + cfg.delta_theta_per_metre * travel
            + cfg.delta_per_correction * turned
        )
        return min(cfg.delta, delta), min(cfg.delta_theta, delta_theta)

    def _next_radii(
        self, start: FloatArray, best: FloatArray, best_d: float, delta: float, delta_theta: float
    ) -> tuple[float, float] | None:
        """Radii of another search stage around ``best``, or ``None`` when done.

        A stage that ends over ``lost_threshold`` is followed by one with the full radii; one
        whose best pose moved most of the way to the edge of its radii, by one with the radii
        doubled (the error may be larger than the odometry suggested).
        """
        cfg = self.config
        if not cfg.adaptive or cfg.mode == "paper":
            return None
        if delta >= cfg.delta and delta_theta >= cfg.delta_theta:
            return None
        if best_d > cfg.lost_above:
            return cfg.delta, cfg.delta_theta
        moved = math.hypot(float(best[0] - start[0]), float(best[1] - start[1]))
        turned = abs(float(best[2] - start[2]))
        if (
            moved > cfg.expand_fraction * delta
            or turned > cfg.expand_fraction * delta_theta
            or best_d > cfg.surprise_ratio * self._typical
        ):
            return min(cfg.delta, 2.0 * delta), min(cfg.delta_theta, 2.0 * delta_theta)
        return None


class _Scorer:
    """A search's comparison: the problem's discrepancy, with the area's cap widened to the
    round's radius when ``widen = (cap, per_radius)`` is given. When the cap changes between
    rounds, the best pose so far is scored again under the new cap, so that a round's
    candidates and the best they must beat are compared alike."""

    def __init__(
        self, problem: _Problem, search: RandomSearch, widen: tuple[float, float] | None
    ) -> None:
        self._problem = problem
        self._search = search
        self._widen = widen
        self._cap: float | None = None if widen is None else widen[0]

    def __call__(self, poses: FloatArray) -> FloatArray:
        if self._widen is None:
            return self._problem.score(poses)
        cap = max(self._widen[0], self._widen[1] * self._search.delta)
        if cap != self._cap:
            self._cap = cap
            search = self._search
            search.best_d = float(self._problem.score(search.best[None], cap)[0])
        return self._problem.score(poses, cap)


def _better(a: Refinement, b: Refinement, scale: float) -> bool:
    """Whether fit ``a`` explains the scan better than ``b``: the lower Cauchy cost of the
    residuals at one common ``scale`` (a beam that hits nothing counts as off by ``4 scale``)."""
    return _robust_cost(a.residuals, scale) < _robust_cost(b.residuals, scale)


def _robust_cost(residuals: FloatArray, scale: float) -> float:
    u = np.nan_to_num(residuals, nan=4.0 * scale) / scale
    return float(np.log1p(u * u).sum())


def _compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a (+) b`` for one pose each, without numpy's per-call overhead."""
    c, s = math.cos(float(a[2])), math.sin(float(a[2]))
    x, y = float(b[0]), float(b[1])
    return np.array(
        [a[0] + c * x - s * y, a[1] + s * x + c * y, wrap_scalar(float(a[2]) + float(b[2]))]
    )


def _pose3(p: ArrayLike) -> FloatArray:
    arr = np.array(p, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not all(map(math.isfinite, arr.tolist())):
        raise ValueError(f"a pose must be 3 finite numbers (x, y, theta), got {arr.tolist()}")
    return arr
