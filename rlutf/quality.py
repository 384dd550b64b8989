"""How good a pose is, in the two numbers a fleet manager asks for (VDA 5050's ``agvPosition``).

* :func:`deviation_range`: the radius around the estimated position that holds the true one
  with 95 % probability, from the position block of the pose's covariance (the refinement's
  Cramer-Rao covariance, :mod:`rlutf.refine`). For a Gaussian error with covariance
  eigenvalues ``l1 >= l2`` the probability inside radius ``r`` is, over the direction ``phi``
  of the standard normal vector, ``1 - mean(exp(-r^2 / (2 (l1 cos^2 phi + l2 sin^2 phi))))``;
  the radius of 95 % is ``k(sqrt(l2 / l1)) sqrt(l1)``, with ``k`` between 1.96 (a line) and
  2.45 (a circle), tabulated once and interpolated.
* :func:`localization_score`: in [0, 1]; 1 when the scan fits the map as well as this robot's
  scans usually do and the pose is well determined, under 0.5 when the localizer calls the
  pose ``lost``, 0 when nothing fits.

A lost pose is a guess: its range is the farthest the robot can be on the map (the distance to
the farthest corner of the map's bounds), so that the range never claims what is not known.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: The probability :func:`deviation_range` covers.
PROBABILITY = 0.95
#: The highest score of a lost pose (the score of a lost pose that fits as well as the floor).
LOST_SCORE = 0.45
_TABLE_SIZE = 257


def _coverage_factors(size: int, probability: float) -> FloatArray:
    """``k`` at ``size`` evenly spaced sigma ratios ``sqrt(l2 / l1)`` in [0, 1] (bisection)."""
    phi = (np.arange(256) + 0.5) * (math.pi / 256.0)
    ratio = np.linspace(0.0, 1.0, size)[:, None]
    v = np.cos(phi) ** 2 + ratio * ratio * np.sin(phi) ** 2
    lo, hi = np.full(size, 1.0), np.full(size, 3.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        inside = 1.0 - np.mean(np.exp(-(mid * mid)[:, None] / (2.0 * v)), axis=1)
        below = inside < probability
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return hi


_FACTORS: list[float] = _coverage_factors(_TABLE_SIZE, PROBABILITY).tolist()


def coverage_factor(ratio: float) -> float:
    """``k`` such that ``k sqrt(l1)`` holds 95 % of a Gaussian whose sigmas are ``sqrt(l1)`` and
    ``ratio sqrt(l1)`` (``ratio`` in [0, 1])."""
    t = min(max(ratio, 0.0), 1.0) * (_TABLE_SIZE - 1)
    i = min(int(t), _TABLE_SIZE - 2)
    f = t - i
    return _FACTORS[i] + f * (_FACTORS[i + 1] - _FACTORS[i])


def deviation_range(covariance: FloatArray | None, fallback: float) -> float:
    """The radius around the position that holds the true one with 95 % probability, metres.

    Args:
        covariance: ``(3, 3)`` covariance of ``(x, y, theta)`` (only the position block is
            used), or ``None``.
        fallback: the range when there is no usable covariance, metres.
    """
    if covariance is None:
        return fallback
    a, b, c = covariance.item(0, 0), covariance.item(0, 1), covariance.item(1, 1)
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
        return fallback
    mean, half = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    l1, l2 = mean + half, max(mean - half, 0.0)
    if not l1 > 0.0:
        return 0.0
    return coverage_factor(math.sqrt(l2 / l1)) * math.sqrt(l1)


def farthest_on_map(x: float, y: float, bounds: tuple[float, float, float, float]) -> float:
    """The distance from ``(x, y)`` to the farthest corner of ``bounds`` (``minx, miny, maxx,
    maxy``): where a robot may be when its pose is not known."""
    dx = max(abs(x - bounds[0]), abs(x - bounds[2]))
    dy = max(abs(y - bounds[1]), abs(y - bounds[3]))
    return math.hypot(dx, dy)


def localization_score(
    fit: float,
    floor: float,
    typical: float,
    deviation: float,
    lost: bool,
    determined: float,
) -> float:
    """The localization score of a pose, in [0, 1].

    The fit term: a lost pose scores ``LOST_SCORE fit / floor`` (under 0.5); any other rises
    from 0.5 at ``floor`` to 1 at ``typical``. It is multiplied by how well the position is
    determined, ``1 / (1 + (deviation / determined)^2)``: 0.5 at a 95 % range of
    ``determined`` metres.

    Args:
        fit: share of the scan's returns that fit the map at the pose.
        floor: the share under which the localizer calls the pose lost.
        typical: the share this robot's scans usually fit (NaN: not known yet).
        deviation: the pose's 95 % range, metres.
        lost: the localizer called the pose lost.
        determined: the range at which the determination halves the score, metres.
    """
    if not math.isfinite(fit):
        return 0.0
    fit = min(max(fit, 0.0), 1.0)
    if lost:
        term = LOST_SCORE * (min(fit / floor, 1.0) if floor > 0.0 else 1.0)
    elif not math.isfinite(typical) or typical <= floor or fit >= typical:
        term = 1.0
    else:
        term = 0.5 + 0.5 * max(fit - floor, 0.0) / (typical - floor)
    spread = deviation / determined if math.isfinite(deviation) else math.inf
    return term / (1.0 + spread * spread)


def pose_quality(
    fit: float,
    covariance: FloatArray | None,
    position: tuple[float, float],
    bounds: tuple[float, float, float, float],
    lost: bool,
    floor: float,
    typical: float,
    determined: float,
) -> tuple[float, float]:
    """``(localization score, deviation range)`` of a pose.

    Args:
        fit: share of the scan's returns that fit the map at the pose.
        covariance: ``(3, 3)`` the pose's covariance, or ``None``.
        position: ``(x, y)`` of the pose, metres.
        bounds: the map's ``(minx, miny, maxx, maxy)``.
        lost: the localizer called the pose lost (its range: anywhere on the map; its score
            from the fit and the covariance as for any other).
        floor: the fit share under which the localizer calls a pose lost.
        typical: the share this robot's scans usually fit.
        determined: see :func:`localization_score`.
    """
    unknown = farthest_on_map(position[0], position[1], bounds)
    fitted = deviation_range(covariance, unknown)
    # A lost pose's range is the whole map; its score still tells a pose a person hides part
    # of the scan at (the fit nearly there) from one that fits nowhere.
    score = localization_score(fit, floor, typical, fitted, lost, determined)
    return score, unknown if lost else fitted
