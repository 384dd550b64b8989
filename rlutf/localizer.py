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
   radii and repeats until ``epsilon`` is met, the radius falls under ``delta_min``, or
   ``max_rounds`` rounds were used.

Randomness comes from a seeded :class:`numpy.random.Generator` owned by the localizer, so the
same seed and inputs give the same poses bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.discrepancy import anchored_turning, polar_area, turning_steps
from rlutf.errors import ConfigError
from rlutf.map import Map
from rlutf.motion import compose, wrap_scalar
from rlutf.raycast import Beams, cast_rays
from rlutf.scan import Scan, beam_points, needs_origin, simplify_ring

FloatArray = NDArray[np.float64]

Mode = Literal["default", "paper"]
DiscrepancyKind = Literal["turning", "area", "combined"]
Status = Literal["tracking", "corrected", "lost"]


@dataclass(frozen=True)
class LocalizerConfig:
    """Every parameter of the localizer, with its unit.

    Attributes:
        mode: ``"default"`` or ``"paper"`` (Algorithm 1 read literally: perimeter-normalised
            turning functions, no elitism, fixed initial radius).
        discrepancy: ``"turning"`` (anchored turning function, radians), ``"area"`` (area between
            the polygons over the perimeter, metres) or ``"combined"`` (turning plus
            ``area_weight`` times area).
        epsilon: accept a pose whose discrepancy is under this (the discrepancy's unit).
        lost_threshold: a best discrepancy over this gives status ``lost``.
        candidates: random candidates per search round (the paper uses 3).
        delta: initial search radius in position, metres.
        delta_theta: initial search radius in heading, radians.
        delta_min: the search stops when the position radius falls under this, metres.
        max_rounds: most search rounds per update.
        adaptive: start the search with radii proportional to the odometry motion (default
            mode only); the full radii are used when that search ends over ``lost_threshold``.
        delta_start: smallest adaptive position radius, metres.
        delta_per_metre: adaptive position radius per metre travelled.
        delta_theta_start: smallest adaptive heading radius, radians.
        delta_theta_per_radian: adaptive heading radius per radian turned.
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
    epsilon: float = 0.006
    lost_threshold: float = 0.1
    candidates: int = 3
    delta: float = 0.3
    delta_theta: float = 0.12
    delta_min: float = 0.003
    max_rounds: int = 10
    adaptive: bool = True
    delta_start: float = 0.03
    delta_per_metre: float = 0.15
    delta_theta_start: float = 0.015
    delta_theta_per_radian: float = 0.1
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
        if self.candidates < 1:
            raise ConfigError(f"candidates: must be at least 1, got {self.candidates}")
        if self.max_rounds < 0:
            raise ConfigError(f"max_rounds: must be at least 0, got {self.max_rounds}")
        if self.simplify_tolerance < 0:
            raise ConfigError(f"simplify_tolerance: must be >= 0, got {self.simplify_tolerance}")
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
            delta=0.04,
            delta_theta=0.03,
            delta_min=0.001,
            max_rounds=12,
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
    """What one update compares against: the real polygon and the beams to cast."""

    def __init__(self, world: Map, scan: Scan, config: LocalizerConfig) -> None:
        valid = scan.valid()
        angles = scan.angles[valid]
        self.count = int(valid.sum())
        self.world = world
        self.config = config
        self.offset = scan.sensor_offset
        self.beams = Beams.of(angles)
        self.range_max = scan.range_max
        self.real_ranges = scan.ranges[valid]
        points = beam_points(self.real_ranges, self.beams.cos, self.beams.sin, self.offset)
        self.closing = needs_origin(angles, scan.covers_full_circle(), config.max_gap)
        real = np.vstack([points, self.offset[None, :2]]) if self.closing else points
        if config.discrepancy != "area":
            self.real_steps = turning_steps(simplify_ring(real, config.simplify_tolerance))

    def score(self, poses: FloatArray) -> FloatArray:
        """``(K,)`` discrepancies of ``(K, 3)`` poses; ``inf`` outside the free space."""
        inside = self.world.contains(poses[:, :2])
        out = np.full(len(poses), np.inf)
        if not inside.any():
            return out
        cand = poses[inside]
        sensors = compose(cand, self.offset)
        ranges = cast_rays(self.world, sensors, self.beams, self.range_max)
        np.minimum(ranges, self.range_max, out=ranges)
        kind = self.config.discrepancy
        if kind == "area":
            out[inside] = polar_area(ranges, self.real_ranges, self.beams.angles, self.closing)
            return out
        rings = beam_points(ranges, self.beams.cos, self.beams.sin, self.offset)
        if self.closing:
            origin = np.broadcast_to(self.offset[:2], (len(cand), 1, 2))
            rings = np.concatenate([rings, origin], axis=1)
        d = anchored_turning(
            turning_steps(rings), self.real_steps, normalise=self.config.mode == "paper"
        )
        if kind == "combined":
            d = d + self.config.area_weight * polar_area(
                ranges, self.real_ranges, self.beams.angles, self.closing
            )
        out[inside] = d
        return out


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
        predicted = compose(self._pose, mot)
        problem = _Problem(self._map, scan, cfg)
        if problem.count < cfg.min_returns:
            inside = bool(self._map.contains(predicted[None, :2])[0])
            self._pose = predicted if inside else self._pose
            return LocalizeResult(self._pose.copy(), math.inf, 0, "lost", 0)

        best = predicted
        best_d = float(problem.score(predicted[None])[0])
        evaluations = 1
        rounds = 0
        if best_d >= cfg.epsilon:
            radii = [(cfg.delta, cfg.delta_theta)]
            if cfg.adaptive and cfg.mode != "paper":
                travel = math.hypot(float(mot[0]), float(mot[1]))
                turn = abs(float(mot[2]))
                small = (
                    min(cfg.delta, cfg.delta_start + cfg.delta_per_metre * travel),
                    min(cfg.delta_theta, cfg.delta_theta_start + cfg.delta_theta_per_radian * turn),
                )
                radii = [small, (cfg.delta, cfg.delta_theta)]
            for stage, (delta, delta_theta) in enumerate(radii):
                if stage > 0 and best_d <= cfg.lost_threshold:
                    break
                best, best_d, used, scored = self._search(problem, best, best_d, delta, delta_theta)
                rounds += used
                evaluations += scored
        if not math.isfinite(best_d):
            best = self._pose
        if rounds == 0 and best_d < cfg.epsilon:
            status: Status = "tracking"
        elif best_d <= cfg.lost_threshold:
            status = "corrected"
        else:
            status = "lost"
        self._pose = np.array([best[0], best[1], wrap_scalar(float(best[2]))])
        return LocalizeResult(self._pose.copy(), best_d, rounds, status, evaluations)

    def _search(
        self,
        problem: _Problem,
        start: FloatArray,
        start_d: float,
        delta: float,
        delta_theta: float,
    ) -> tuple[FloatArray, float, int, int]:
        cfg = self.config
        elitist = cfg.mode != "paper"
        best, best_d = start, start_d
        rounds = 0
        scored = 0
        while rounds < cfg.max_rounds and delta >= cfg.delta_min and best_d >= cfg.epsilon:
            k = cfg.candidates
            u = self._rng.random((k, 3))
            radius = delta * np.sqrt(u[:, 0])
            bearing = 2.0 * math.pi * u[:, 1]
            cand = np.empty((k, 3))
            cand[:, 0] = best[0] + radius * np.cos(bearing)
            cand[:, 1] = best[1] + radius * np.sin(bearing)
            cand[:, 2] = best[2] + delta_theta * (2.0 * u[:, 2] - 1.0)
            d = problem.score(cand)
            scored += k
            i = int(np.argmin(d))
            if math.isfinite(float(d[i])) and (not elitist or float(d[i]) < best_d):
                best, best_d = cand[i], float(d[i])
            delta *= 0.5
            delta_theta *= 0.5
            rounds += 1
        return best, best_d, rounds, scored


def _pose3(p: ArrayLike) -> FloatArray:
    arr = np.array(p, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ValueError(f"a pose must be 3 finite numbers (x, y, theta), got {arr.tolist()}")
    return arr
