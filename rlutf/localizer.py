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
   pose's covariance (:mod:`rlutf.refine`); on a map traced from a grid, steps 2 to 4 run on
   its walls simplified at ``coarse_tolerance`` (fewer small local minima), and the answer is
   the refinement on the map itself from that pose or from the prediction, the better one;
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
best fit is kept. Randomness comes from a seeded :class:`numpy.random.Generator` owned by the
localizer, so the same seed and inputs give the same poses bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rlutf.config import LocalizerConfig, Status
from rlutf.field import WideSearch, wide_search
from rlutf.map import Map, coarse_map
from rlutf.mapchange import Returns
from rlutf.motion import wrap_scalar
from rlutf.problem import Problem
from rlutf.quality import farthest_on_map, pose_quality
from rlutf.raycast import Beams
from rlutf.refine import Refinement, refine_pose
from rlutf.relocalize import (
    Follower,
    FollowSettings,
    Hypothesis,
    RelocalizeSettings,
    robust_cost,
)
from rlutf.result import LocalizeResult
from rlutf.scan import Scan
from rlutf.search import RandomSearch
from rlutf.stages import search_stages, stage_search

__all__ = ["LocalizeResult", "Localizer", "LocalizerConfig", "Status"]

FloatArray = NDArray[np.float64]


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
        # The map and the map tracked on (tracking_map), found once per map.
        self._tracking: tuple[Map, Map] | None = None
        # Size of the last correction (position, heading): scales the next search.
        self._correction = (0.0, 0.0)
        # Running typical discrepancy at the corrected pose: a much larger one is a surprise.
        self._typical = math.inf
        self._previous: Problem | None = None
        self._spread: tuple[float, float] | None = self._spread_of(spread)
        self._refine_settings = self.config.refine_settings()
        # A relocalization under way, and the lost updates in a row that may start one.
        self._follower: Follower | None = None
        self._lost_run = 0
        # Running typical share of the returns that fit (not lost updates); on probation?
        self._typical_fit = math.nan
        self._fit_deviation = 0.0
        self._probation = False
        # A seeded pose (initial pose, handover, restart) is a claim until a scan fits it.
        self._unverified = True

    @property
    def pose(self) -> FloatArray:
        """``(3,)`` current pose estimate (a copy)."""
        return self._pose.copy()

    @property
    def map(self) -> Map:
        """The map the robot is on."""
        return self._map

    @property
    def tracking_map(self) -> Map:
        """The map the tracking's search and first refinement run on: the map's walls
        simplified at ``coarse_tolerance`` (:func:`rlutf.map.coarse_map`), or the map itself
        (no ``refine``, the paper's mode, a tolerance of 0, or a map whose walls barely
        simplify: a drawn one)."""
        cfg = self.config
        if not cfg.refine or cfg.mode == "paper":
            return self._map
        found = self._tracking
        if found is None or found[0] is not self._map:
            found = self._tracking = (self._map, coarse_map(self._map, cfg.coarse_tolerance))
        return found[1]

    def reset(self, pose: ArrayLike, spread: tuple[float, float] | None = None) -> None:
        """Re-seed the pose (an operator's initial pose); the next update searches ``spread``
        around it (``None``: the config's ``spread`` and ``spread_heading``)."""
        self._pose = _pose3(pose)
        self._correction = (0.0, 0.0)
        self._typical = math.inf
        self._typical_fit = math.nan
        self._fit_deviation = 0.0
        self._probation = False
        self._spread = self._spread_of(spread)
        self._follower = None
        self._lost_run = 0
        self._unverified = True

    def set_map(self, world: Map) -> None:
        """Switch to a new version of the map, keeping the pose."""
        self._map = world
        if self._follower is not None:
            self._follower.world = world

    def relocalize(self, region: tuple[float, float, float] | None = None) -> None:
        """Forget the pose: the next updates find the robot on the whole map (or in the circle
        ``region = (x, y, radius)``), following several hypotheses over the next scans while
        the place is ambiguous (:mod:`rlutf.relocalize`)."""
        cfg = self.config
        if region is not None:
            x, y, radius = (float(v) for v in region)
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(radius)) or radius <= 0:
                raise ValueError(f"region: expected finite x, y and radius > 0, got {region}")
            region = (x, y, radius)
        search = RelocalizeSettings(
            resolution=cfg.relocalize_resolution,
            accept_fit=cfg.relocalize_fit,
            fit_distance=cfg.fit_distance,
            select_scale=cfg.select_scale,
        )
        follow = FollowSettings(
            min_fit=cfg.min_fit,
            accept_fit=cfg.relocalize_fit,
            win_margin=cfg.win_margin,
            follow_scans=cfg.follow_scans,
            widen_after=cfg.relocalize_after,
        )
        self._follower = Follower(self._map, region, search, follow, self._refine_settings)
        self._spread = None
        self._lost_run = 0
        self._typical_fit = math.nan
        self._fit_deviation = 0.0
        self._probation = False

    @property
    def relocalizing(self) -> bool:
        """A relocalization is under way."""
        return self._follower is not None

    @property
    def searched_region(self) -> tuple[float, float, float] | None:
        """The circle a relocalization under way searches (``None``: the whole map, or none)."""
        return None if self._follower is None else self._follower.region

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
        problem = Problem(self._map, scan, cfg, self._scan_beams(scan))
        if problem.count < cfg.min_returns:
            inside = bool(self._map.contains(predicted[None, :2])[0])
            self._pose = predicted if inside else self._pose
            return LocalizeResult(
                self._pose.copy(),
                math.inf,
                0,
                "lost",
                0,
                relocalizing=self._follower is not None,
                deviation_range=self._unknown_range(self._pose),
            )
        if self._follower is not None:
            return self._relocalizing(problem, predicted, mot, scan)

        wide = cfg.wide_search and cfg.mode != "paper"
        spread, self._spread = self._spread, None
        if wide and spread is not None and spread[0] + spread[1] > 0:
            best, rounds, evaluations, fit = self._wide(problem, predicted, spread)
        else:
            track = self.tracking_map
            first = problem if track is self._map else problem.on(track)
            gate = cfg.refine and problem.cap is not None and cfg.mode != "paper"
            fit = self._fit(first, predicted, gate=gate)
            if gate and not fit.gated:
                # Algorithm 1's step 4: the prediction fits; the refinement started from it.
                best, rounds, evaluations = predicted, 0, 1
            else:
                # Algorithm 1's comparison and random search
                start_d = fit.area_start if gate else None
                best, rounds, evaluations = search_stages(
                    cfg, self._rng, first, predicted, mot, self._correction, self._typical, start_d
                )
                fit = self._fit(first, best)
            if first is not problem:
                fit = self._finish(problem, fit, predicted)
            if wide and fit.fit < cfg.min_fit:
                # The prediction's basin does not fit the scan: odometry slipped or jumped.
                # Look wider before calling the robot lost; a pose found so is on probation
                # (it must fit about as well as this robot's poses usually do), as a robot
                # carried off may find a place like its own near where it was.
                other, r2, e2, other_fit = self._wide(
                    problem, predicted, (cfg.spread, cfg.spread_heading)
                )
                evaluations += e2
                self._probation = True
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
        # Python floats: the same IEEE operations as on numpy's scalars, at a tenth of the cost.
        x, y, heading = pose.tolist()
        px, py, ph = predicted.tolist()
        self._correction = (math.hypot(x - px, y - py), abs(wrap_scalar(heading - ph)))
        floor = cfg.min_fit
        if math.isfinite(self._typical_fit):
            margin = min(max(cfg.fit_deviations * self._fit_deviation, 0.05), cfg.fit_margin)
            if self._probation:
                margin = min(margin, cfg.probation_margin)
            floor = max(floor, self._typical_fit - margin)
        verifying = self._unverified and cfg.mode != "paper"
        if verifying:
            floor = max(floor, cfg.seed_fit)
        typical_fit = self._typical_fit
        if share < floor:
            status: Status = "lost"
            # Look wider at the next scan (default mode): a lost robot comes back by itself,
            # and one still lost after relocalize_after updates searches the whole map.
            self._spread = (cfg.spread, cfg.spread_heading) if wide else None
            self._probation = True
            self._lost_run += 1
            if cfg.relocalize_after and (verifying or self._lost_run >= cfg.relocalize_after):
                # A seed that the scan does not confirm is no place to search around: a robot
                # handed over (or restarted, or placed) from a wrong pose would otherwise be
                # "corrected" to a place near it that fits half of its beams.
                self.relocalize()
        else:
            status = "tracking" if rounds == 0 else "corrected"
            self._unverified = False
            self._lost_run = 0
            self._probation = False
            rate = cfg.typical_rate
            if math.isfinite(self._typical_fit):
                self._fit_deviation += rate * (abs(share - self._typical_fit) - self._fit_deviation)
                self._typical_fit += rate * (share - self._typical_fit)
            else:
                self._typical_fit = share
        self._pose = np.array([x, y, wrap_scalar(heading)])
        score, deviation = self._quality(fit, status == "lost", floor, typical_fit)
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
            score=score,
            deviation_range=deviation,
            returns=Returns(
                self._pose,
                problem.offset,
                problem.beams.cos,
                problem.beams.sin,
                problem.real_ranges,
                fit.ranges,
            ),
            fit_needed=floor,
        )

    def _relocalizing(
        self, problem: Problem, predicted: FloatArray, mot: FloatArray, scan: Scan
    ) -> LocalizeResult:
        """An update of a relocalization: the map searched, or its hypotheses followed."""
        follower = self._follower
        assert follower is not None
        step = follower.step(mot, scan, lambda pose: self._fit(problem, pose))
        fit = step.best
        hypotheses: tuple[Hypothesis, ...] = ()
        if step.winner is not None:
            self._follower = None
            status: Status = "corrected"
        else:
            status = "lost"
            hypotheses = step.hypotheses
        if fit is None:
            # Nothing fits anywhere: carry the pose by odometry and search again next scan.
            self._pose = predicted
            at = float(problem.score(predicted[None])[0])
            return LocalizeResult(
                predicted.copy(),
                at if math.isfinite(at) else 1e9,
                0,
                "lost",
                step.nodes,
                fit=0.0,
                relocalizing=True,
                deviation_range=self._unknown_range(predicted),
            )
        pose = fit.pose
        self._pose = np.array([pose[0], pose[1], wrap_scalar(float(pose[2]))])
        self._correction = (0.0, 0.0)
        self._typical = math.inf
        self._lost_run = 0
        discrepancy = float(problem.of_ranges(fit.ranges[None])[0])
        # A hypothesis that wins must fit relocalize_fit of the returns; until one wins, the
        # place is not known.
        score, deviation = self._quality(
            fit, status == "lost", self.config.min_fit, self.config.relocalize_fit
        )
        return LocalizeResult(
            self._pose.copy(),
            discrepancy if math.isfinite(discrepancy) else math.inf,
            0,
            status,
            step.nodes + len(step.hypotheses),
            fit.covariance,
            fit.fit,
            fit.sigma,
            fit.casts,
            hypotheses,
            True,
            score,
            deviation,
        )

    def _quality(
        self, fit: Refinement, lost: bool, floor: float, typical: float
    ) -> tuple[float, float]:
        """``(score, deviation range)`` at the pose just set; ``typical``: NaN if not known."""
        cfg = self.config
        typical = typical if math.isfinite(typical) else cfg.relocalize_fit
        x, y, _ = self._pose.tolist()
        return pose_quality(
            fit.fit, fit.covariance, (x, y), self._map.bounds, lost, floor, typical,
            cfg.quality_range,
        )  # fmt: skip

    def _unknown_range(self, pose: FloatArray) -> float:
        """The deviation range of a pose that is not known: anywhere on the map."""
        return farthest_on_map(float(pose[0]), float(pose[1]), self._map.bounds)

    def _fit(self, problem: Problem, pose: FloatArray, gate: bool = False) -> Refinement:
        """The refinement from ``pose`` (or, without ``refine``, ``pose`` evaluated); with
        ``gate``, only if the polar area at ``pose`` is under ``epsilon``."""
        cfg = self.config
        return refine_pose(
            problem.world,
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

    def _finish(self, problem: Problem, coarse: Refinement, predicted: FloatArray) -> Refinement:
        """The answer on the map after a pose found on the simplified walls: the refinement on
        the map from that pose, or the one from the prediction if it explains the scan better
        (a prediction already at the bottom of the map's own basin, where the simplified walls
        would only move it away: a good odometry step on a clean map)."""
        fit = self._fit(problem, coarse.pose)
        other = self._fit(problem, predicted)
        return other if _better(other, fit, self.config.select_scale) else fit

    def _wide(
        self, problem: Problem, predicted: FloatArray, spread: tuple[float, float]
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
        """The random search of one stage (:func:`rlutf.stages.stage_search`)."""
        return stage_search(self.config, self._rng, start, delta, delta_theta)


def _better(a: Refinement, b: Refinement, scale: float) -> bool:
    """Whether fit ``a`` explains the scan better than ``b``: the lower Cauchy cost of the
    residuals at one common ``scale`` (a beam that hits nothing counts as off by ``4 scale``)."""
    return robust_cost(a.residuals, scale) < robust_cost(b.residuals, scale)


def _compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a (+) b`` for one pose each, without numpy's per-call overhead."""
    ax, ay, at = a.tolist()
    x, y, bt = b.tolist()
    c, s = math.cos(at), math.sin(at)
    return np.array([ax + c * x - s * y, ay + s * x + c * y, wrap_scalar(at + bt)])


def _pose3(p: ArrayLike) -> FloatArray:
    arr = np.array(p, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not all(map(math.isfinite, arr.tolist())):
        raise ValueError(f"a pose must be 3 finite numbers (x, y, theta), got {arr.tolist()}")
    return arr
