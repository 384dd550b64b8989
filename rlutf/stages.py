"""Algorithm 1's random search, stage after stage, as the localizer runs it.

The first stage's radii follow the odometry motion and the previous correction (default mode);
a stage whose best pose moved most of the way to the edge of its radii, or whose discrepancy is
well over the robot's typical one, is followed by one with doubled radii (the full radii when
over ``lost_threshold``). In the paper's mode there is one stage, with the configured radii. The
functions take the localizer's parameters and state as arguments and change nothing but the
generator's state, so that the same seed and inputs give the same poses bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from rlutf.config import LocalizerConfig
from rlutf.problem import Problem, Scorer
from rlutf.search import RandomSearch

__all__ = ["initial_radii", "next_radii", "search_stages", "stage_search"]

FloatArray = NDArray[np.float64]


def search_stages(
    cfg: LocalizerConfig,
    rng: np.random.Generator,
    problem: Problem,
    predicted: FloatArray,
    mot: FloatArray,
    correction: tuple[float, float],
    typical: float,
    scored: float | None = None,
) -> tuple[FloatArray, int, int]:
    """Algorithm 1's comparison and random search: ``(best pose, rounds, evaluations)``.

    Args:
        cfg: the localizer's parameters.
        rng: the localizer's generator (drawn from).
        problem: the scan against the map.
        predicted: the prediction.
        mot: the odometry motion since the previous update.
        correction: ``(metres, radians)`` of the previous update's correction.
        typical: the robot's recent typical discrepancy (``inf`` when not known).
        scored: the prediction's discrepancy, if known.
    """
    best = predicted
    best_d = float(problem.score(predicted[None])[0]) if scored is None else scored
    evaluations = 1
    rounds = 0
    if best_d < cfg.accept_below:
        return best, rounds, evaluations
    delta, delta_theta = initial_radii(cfg, mot, correction)
    for _stage in range(max(cfg.max_stages, 1)):
        start = best
        search = stage_search(cfg, rng, start, delta, delta_theta)
        search.best_d = best_d
        score = _scorer(cfg, problem, search)
        evaluations += search.run(score)
        best, best_d = search.best, search.best_d
        if not math.isfinite(best_d):
            break
        rounds += search.rounds
        radii = next_radii(cfg, start, best, best_d, delta, delta_theta, typical)
        if radii is None:
            break
        delta, delta_theta = radii
    return best, rounds, evaluations


def _scorer(cfg: LocalizerConfig, problem: Problem, search: RandomSearch) -> Scorer:
    if problem.cap is None or cfg.mode == "paper" or cfg.cap_per_radius == 0:
        return Scorer(problem, search, None)
    return Scorer(problem, search, (problem.cap, cfg.cap_per_radius))


def stage_search(
    cfg: LocalizerConfig,
    rng: np.random.Generator,
    start: FloatArray,
    delta: float,
    delta_theta: float,
) -> RandomSearch:
    """The random search of one stage around ``start``."""
    paper = cfg.mode == "paper"
    return RandomSearch(
        rng,
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


def initial_radii(
    cfg: LocalizerConfig, mot: FloatArray, correction: tuple[float, float]
) -> tuple[float, float]:
    """Search radii (position, heading) of the first stage."""
    if not cfg.adaptive or cfg.mode == "paper":
        return cfg.delta, cfg.delta_theta
    travel = math.hypot(float(mot[0]), float(mot[1]))
    turn = abs(float(mot[2]))
    moved, turned = correction
    delta = cfg.delta_start + cfg.delta_per_metre * travel + cfg.delta_per_correction * moved
    delta_theta = (
        cfg.delta_theta_start
        + cfg.delta_theta_per_radian * turn
        + cfg.delta_theta_per_metre * travel
        + cfg.delta_per_correction * turned
    )
    return min(cfg.delta, delta), min(cfg.delta_theta, delta_theta)


def next_radii(
    cfg: LocalizerConfig,
    start: FloatArray,
    best: FloatArray,
    best_d: float,
    delta: float,
    delta_theta: float,
    typical: float,
) -> tuple[float, float] | None:
    """Radii of another search stage around ``best``, or ``None`` when done.

    A stage that ends over ``lost_threshold`` is followed by one with the full radii; one
    whose best pose moved most of the way to the edge of its radii, by one with the radii
    doubled (the error may be larger than the odometry suggested).
    """
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
        or best_d > cfg.surprise_ratio * typical
    ):
        return min(cfg.delta, 2.0 * delta), min(cfg.delta_theta, 2.0 * delta_theta)
    return None
