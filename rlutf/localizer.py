"""The RLuTF localizer: the paper's Algorithm 1 with its open points resolved.

One :class:`Localizer` tracks one robot on one map. Each :meth:`Localizer.update` takes the
odometry motion since the previous scan and the new scan, and

1. predicts ``Ov_new = Or_old (+) motion``;
2. builds the virtual polygon ``Pv`` by casting the scan's own beams (those with a return) from
   the prediction, and the real polygon ``Pr`` from the scan;
3. scores them with the configured discrepancy;
4. accepts the prediction if the discrepancy is under ``epsilon``; otherwise samples
   ``candidates`` random poses within ``delta`` (position) and ``delta_theta`` (heading) of the
   current best, keeps the best (the current best too, unless ``mode == "paper"``), halves the
   radii and repeats until ``epsilon`` is met, the radii fall under ``delta_min`` (and, in the
   default mode, ``delta_theta_min``), or ``max_rounds`` rounds were used.

In the default mode the first radii follow the odometry motion and the previous correction, and
a search that ends at the edge of its radii, or with a discrepancy well over the recent typical
one, is followed by another around its best with doubled radii (the full radii when over
``lost_threshold``). The area discrepancy caps each beam's share (``area_cap``), so that beams
grazing an edge or hitting people cannot dominate it.

All candidates of one search lie within twice its initial radii of its start, so one
:class:`~rlutf.raycast.RegionCaster` per search prepares the ray casting once, and the
prediction is scored together with the first round's candidates.

Randomness comes from a seeded :class:`numpy.random.Generator` owned by the localizer, so the
same seed and inputs give the same poses bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.discrepancy import PolarArea, anchored_turning, turning_steps
from rlutf.errors import ConfigError
from rlutf.map import Map
from rlutf.motion import wrap_scalar
from rlutf.raycast import Beams
from rlutf.region import RegionCaster
from rlutf.scan import Scan, beam_points, needs_origin, simplify_ring
from rlutf.search import RandomSearch

FloatArray = NDArray[np.float64]

Mode = Literal["default", "paper"]
DiscrepancyKind = Literal["turning", "area", "combined"]
Status = Literal["tracking", "corrected", "lost"]


@dataclass(frozen=True)
class LocalizerConfig:
    """Every parameter of the localizer, with its unit.

    Attributes:
        mode: ``"default"`` or ``"paper"`` (Algorithm 1 read literally: perimeter-normalised
            turning functions, no elitism, fixed initial radius, exact area).
        discrepancy: ``"turning"`` (anchored turning function, radians), ``"area"`` (area between
            the polygons over the perimeter, metres) or ``"combined"`` (turning plus
            ``area_weight`` times area).
        epsilon: accept a pose whose discrepancy is under this (the discrepancy's unit). With
            range noise ``s`` the area at the true pose is about ``0.3 s``, so the default
            accepts the prediction only for near-noise-free scans and otherwise searches.
        lost_threshold: a best discrepancy over this gives status ``lost``.
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
            of this width, metres (see :class:`rlutf.discrepancy.PolarArea`); ``None`` uses the
            exact area. ``"combined"`` always uses the exact area.
        simplify_tolerance: Douglas-Peucker tolerance for the real polygon, metres (about two
            to three times the range noise).
        area_weight: weight of the area term in ``"combined"``, radians per metre.
        max_gap: widest angular gap between returns bridged by a polygon edge, radians; past
            it the polygon closes through the sensor.
        min_returns: fewer returns than this give status ``lost`` without a comparison.
        seed: base seed of the random generator.
    """

    mode: Mode = "default"
    discrepancy: DiscrepancyKind = "area"
    epsilon: float = 0.0015
    lost_threshold: float = 0.03
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
    simplify_tolerance: float = 0.03
    area_weight: float = 5.0
    max_gap: float = 0.35
    min_returns: int = 8
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
        positive = ("delta", "delta_theta", "delta_min", "epsilon", "lost_threshold", "max_gap")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: must be positive, got {getattr(self, name)}")
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
        if self.lost_threshold < self.epsilon:
            raise ConfigError("lost_threshold: must be at least epsilon")

    @classmethod
    def paper(cls, **overrides: object) -> LocalizerConfig:
        """The paper's Algorithm 1 as literally as it can be read."""
        base = cls(
            mode="paper",
            discrepancy="area",
            adaptive=False,
            epsilon=0.005,
            lost_threshold=0.1,
            candidates=3,
            delta=0.04,
            delta_theta=0.03,
            delta_min=0.001,
            max_rounds=12,
            area_cap=None,
        )
        return replace(base, **overrides)  # type: ignore[arg-type]


@dataclass(frozen=True)
class LocalizeResult:
    """Outcome of one update.

    Attributes:
        pose: ``(3,)`` the corrected pose ``(x, y, theta)`` in the map frame.
        discrepancy: the discrepancy at ``pose``; ``inf`` when no comparison was possible.
        iterations: search rounds used (0 when the prediction was accepted).
        status: ``tracking``, ``corrected`` or ``lost``.
        evaluations: candidate poses scored, the prediction included.
    """

    pose: FloatArray
    discrepancy: float
    iterations: int
    status: Status
    evaluations: int


class _Problem:
    """What one update compares against: the real scan, its polygon and the beams to cast."""

    def __init__(self, world: Map, scan: Scan, config: LocalizerConfig, beams: Beams) -> None:
        valid = scan.valid()
        self.count = int(np.count_nonzero(valid))
        self.world = world
        self.config = config
        self.offset = scan.sensor_offset
        self.range_max = scan.range_max
        self.caster: RegionCaster | None = None
        if self.count < config.min_returns:
            return
        self.beams = beams.select(valid)
        angles = self.beams.angles
        self.real_ranges = scan.ranges[valid]
        gaps = angles[1:] - angles[:-1]
        np.abs(gaps, out=gaps)
        self.closing = needs_origin(angles, scan.covers_full_circle(), config.max_gap, gaps)
        kind = config.discrepancy
        if kind != "turning":
            # The combined discrepancy keeps the exact area: capped, its turning term (which
            # people and grazed edges disturb the most) would dominate.
            self.area = PolarArea(
                self.real_ranges,
                angles,
                self.closing,
                config.area_cap if kind == "area" else None,
                unit=self.beams.unit,
                gaps=gaps,
            )
        if kind == "area" and config.area_cap is not None:
            # A virtual range past the real one plus the cap counts as the cap, so no beam needs
            # casting farther than the longest return plus the cap (much less wall to look at).
            longest = float(self.real_ranges.max()) + config.area_cap
            self.range_max = min(self.range_max, longest)
        if kind != "area":
            points = beam_points(self.real_ranges, self.beams.cos, self.beams.sin, self.offset)
            real = np.vstack([points, self.offset[None, :2]]) if self.closing else points
            self.real_steps = turning_steps(simplify_ring(real, config.simplify_tolerance))

    def search_region(self, centre: FloatArray, radius: float, heading_radius: float) -> None:
        """Prepare casting from poses within ``radius`` and ``heading_radius`` of ``centre``."""
        self.caster = RegionCaster(
            self.world, self.beams, centre, radius, heading_radius, self.range_max, self.offset
        )

    def score(self, poses: FloatArray) -> FloatArray:
        """``(K,)`` discrepancies of ``(K, 3)`` poses of the search region; ``inf`` outside the
        free space."""
        caster = self.caster
        assert caster is not None, "search_region() first"
        if caster.poses_inside:
            return self._discrepancy(caster.cast(poses))
        inside = self.world.contains(poses[:, :2])
        out = np.full(len(poses), np.inf)
        if inside.any():
            out[inside] = self._discrepancy(caster.cast(poses[inside]))
        return out

    def _discrepancy(self, ranges: FloatArray) -> FloatArray:
        kind = self.config.discrepancy
        if kind == "area":
            return self.area(ranges)
        rings = beam_points(ranges, self.beams.cos, self.beams.sin, self.offset)
        if self.closing:
            origin = np.broadcast_to(self.offset[:2], (len(ranges), 1, 2))
            rings = np.concatenate([rings, origin], axis=1)
        d = anchored_turning(
            turning_steps(rings), self.real_steps, normalise=self.config.mode == "paper"
        )
        if kind == "combined":
            d = d + self.config.area_weight * self.area(ranges)
        return d


class Localizer:
    """Tracks one robot's pose on a map with RLuTF.

    Args:
        world: the map.
        pose: ``(3,)`` initial pose of the robot base in the map frame.
        config: parameters; defaults to :class:`LocalizerConfig`.
        seed: seed of this localizer's generator (e.g. derived from the robot id); combined
            with ``config.seed``.
    """

    def __init__(
        self,
        world: Map,
        pose: ArrayLike,
        config: LocalizerConfig | None = None,
        seed: int = 0,
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

    @property
    def pose(self) -> FloatArray:
        """``(3,)`` current pose estimate (a copy)."""
        return self._pose.copy()

    @property
    def map(self) -> Map:
        """The map the robot is on."""
        return self._map

    def reset(self, pose: ArrayLike) -> None:
        """Re-seed the pose (an operator's initial pose)."""
        self._pose = _pose3(pose)
        self._correction = (0.0, 0.0)
        self._typical = math.inf

    def set_map(self, world: Map) -> None:
        """Switch to a new version of the map, keeping the pose."""
        self._map = world

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

        best, best_d = predicted, math.inf
        rounds = 0
        evaluations = 0
        delta, delta_theta = self._initial_radii(mot)
        for stage in range(max(cfg.max_stages, 1)):
            start = best
            # Every candidate of a search lies within twice the initial radii of its start.
            problem.search_region(start, 2.0 * delta + 1e-9, 2.0 * delta_theta + 1e-9)
            search = self._search(start, delta, delta_theta)
            if stage == 0:
                if cfg.mode == "paper":
                    best_d = float(problem.score(predicted[None])[0])
                    evaluations += 1
                else:
                    # Score the prediction together with the first round's candidates: one cast
                    # instead of two; the candidates are only used if the search runs.
                    cand = search.candidates()
                    d = problem.score(np.concatenate((predicted[None], cand)))
                    best_d = float(d[0])
                    search.pending = (cand, d[1:])
                    evaluations += 1 + len(cand)
                if best_d < cfg.epsilon:
                    break
            search.best_d = best_d
            scored = search.run(problem.score)
            best, best_d = search.best, search.best_d
            rounds += search.rounds
            evaluations += scored
            radii = self._next_radii(start, best, best_d, delta, delta_theta)
            if radii is None:
                break
            delta, delta_theta = radii
        if not math.isfinite(best_d):
            best = self._pose
        elif best_d <= cfg.lost_threshold:
            rate = cfg.typical_rate
            self._typical = (
                best_d
                if not math.isfinite(self._typical)
                else ((1.0 - rate) * self._typical + rate * best_d)
            )
        self._correction = (
            math.hypot(float(best[0] - predicted[0]), float(best[1] - predicted[1])),
            abs(wrap_scalar(float(best[2] - predicted[2]))),
        )
        if rounds == 0 and best_d < cfg.epsilon:
            status: Status = "tracking"
        elif best_d <= cfg.lost_threshold:
            status = "corrected"
        else:
            status = "lost"
        self._pose = np.array([best[0], best[1], wrap_scalar(float(best[2]))])
        # Free the previous update's arrays only now that this one has made its own: freed
        # first, they would leave free memory at the top of the heap, which malloc gives back to
        # the system, and every update would pay page faults to map it again.
        self._previous = problem
        return LocalizeResult(self._pose.copy(), best_d, rounds, status, evaluations)

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
            epsilon=cfg.epsilon,
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
        if best_d > cfg.lost_threshold:
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
