"""Local refinement of a pose: robust least squares on the ranges, and its covariance.

The RLuTF search finds the basin of the right pose; this reaches its bottom. From a start pose,
Levenberg-Marquardt minimises the Cauchy-weighted squared differences between the measured
ranges and the ranges cast from the pose, re-casting every beam at every step, with the exact
Jacobian of a ray-cast range (the hit wall's normal and the incidence angle, Censi 2007, "On
achievable accuracy for range-finder localization"). The robust scale follows the residuals'
median absolute deviation, so beams off by far more than the noise (people, clutter, map
errors, grazed corners) weigh almost nothing, and the range noise comes out of the fit.

At the solution the Fisher information of the inlier beams, scaled by that noise, gives the
covariance: ``sigma^2 (J^T J)^-1``, the Cramer-Rao bound evaluated at the estimate. A weak prior
at the start pose keeps directions that the scan does not constrain (the axis of a featureless
corridor) where they were, and shows in the covariance as the prior's own uncertainty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from rlutf.map import Map
from rlutf.raycast import Beams

FloatArray = NDArray[np.float64]

#: The Cauchy kernel's scale over the noise's sigma for 95 % efficiency on Gaussian noise.
CAUCHY_EFFICIENT = 2.3849
#: ``(weights, real_sq, band, limit)`` of a polar area: see :func:`refine_pose`.
PolarAreaTerms = tuple[FloatArray, FloatArray, FloatArray, float]
_EMPTY = np.empty(0)


@dataclass(frozen=True)
class RefineSettings:
    """Parameters of :func:`refine_pose`.

    Attributes:
        iterations: most casts (each step, tried or taken, casts every beam once).
        tolerance: a step shorter than this (metres) that also turns less than
            ``heading_tolerance`` (radians) is taken without a cast, and ends the refinement.
        sigma_min: smallest range noise assumed, metres (the kernel's scale never goes under
            ``2.38 sigma_min``; keeps a near-perfect fit from rejecting every beam).
        sigma_max: largest range noise assumed at the start, metres (a far-off start pose sees
            large residuals; the scale shrinks as the fit improves).
        max_incidence: beams hitting a wall more obliquely than this (radians from its normal)
            are left out, where a thin ray is a poor model of the beam.
        prior_position: one-sigma width of the weak prior at the start pose, metres.
        prior_heading: the same for the heading, radians.
    """

    iterations: int = 12
    tolerance: float = 1e-3
    heading_tolerance: float = 3e-4
    sigma_min: float = 0.002
    sigma_max: float = 0.2
    max_incidence: float = math.radians(80.0)
    prior_position: float = 0.5
    prior_heading: float = 0.5

    @cached_property
    def prior_information(self) -> FloatArray:
        """``(3,)`` the prior's information per unit variance, ``1 / sigma^2`` per axis (made
        once: every refinement asks; read-only)."""
        p, h = self.prior_position**-2, self.prior_heading**-2
        out = np.array([p, p, h])
        out.flags.writeable = False
        return out

    @cached_property
    def kernel_constants(self) -> tuple[float, float, float]:
        """``(cos(max_incidence), the kernel's smallest scale, its largest)`` as the compiled
        refinement takes them (made once: every refinement asks)."""
        return (
            math.cos(self.max_incidence),
            CAUCHY_EFFICIENT * self.sigma_min,
            CAUCHY_EFFICIENT * self.sigma_max,
        )


@dataclass(frozen=True, eq=False)
class Refinement:
    """Outcome of :func:`refine_pose`.

    Attributes:
        pose: ``(3,)`` the refined pose.
        covariance: ``(3, 3)`` covariance of ``(x, y, theta)``, m^2, m rad and rad^2; ``None``
            when too few beams constrain the pose.
        sigma: the range noise estimated from the residuals (robust), metres.
        ranges: ``(n,)`` the ranges cast from ``pose`` (``inf`` where no wall is hit).
        residuals: ``(n,)`` measured minus cast ranges (NaN where no wall is hit).
        fit: share of the beams whose measured range lies within ``fit_distance`` of the cast
            one.
        casts: casts of the whole scan made.
        used: beams that entered the fit.
        area_start: the polar area of the start pose (with ``area``; NaN without).
        area_final: the polar area of ``pose`` (with ``area``; NaN without).
        gated: the start pose's area was not under ``accept_below``: nothing was refined.
    """

    pose: FloatArray
    covariance: FloatArray | None
    sigma: float
    ranges: FloatArray
    residuals: FloatArray
    fit: float
    casts: int
    used: int
    area_start: float = math.nan
    area_final: float = math.nan
    gated: bool = False


def refine_pose(
    world: Map,
    pose: FloatArray,
    beams: Beams,
    real_ranges: FloatArray,
    sensor_offset: FloatArray,
    max_range: float,
    settings: RefineSettings,
    *,
    fit_distance: float = 0.1,
    iterations: int | None = None,
    area: PolarAreaTerms | None = None,
    accept_below: float = 0.0,
) -> Refinement:
    """Refine ``pose`` against the map.

    Args:
        world: the map.
        pose: ``(3,)`` start pose of the robot base.
        beams: the beams with a return, sensor frame.
        real_ranges: ``(n,)`` their measured ranges, metres.
        sensor_offset: ``(3,)`` sensor pose in the base frame.
        max_range: the sensor's range, metres: beams cast past it hit nothing.
        settings: parameters.
        fit_distance: a beam fits when its measured range is within this of the cast one,
            metres (:attr:`Refinement.fit`).
        iterations: most casts, overriding ``settings.iterations`` (1: only evaluate the start
            pose: its residuals and covariance).
        area: ``(weights, real_sq, band, limit)`` of a polar area
            (:class:`rlutf.discrepancy.PolarArea`) to evaluate at the start and final poses from
            the casts made anyway.
        accept_below: with ``area``, refine only if the start pose's area is under this (else
            return after one cast, ``gated``); 0 refines in any case.

    Returns:
        The refinement.
    """
    from rlutf import _lm

    n = len(beams)
    out_pose = np.empty(3)
    ranges = np.empty(n)
    residuals = np.empty(n)
    covariance = np.empty((3, 3))
    prior = settings.prior_information
    min_cos_incidence, scale_min, scale_max = settings.kernel_constants
    weights, real_sq, band, limit = area if area is not None else (_EMPTY, _EMPTY, _EMPTY, 0.0)
    casts, sigma, used, fitted, ok, d_start, d_final, gated = _lm.refine(
        np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(sensor_offset, dtype=np.float64),
        beams.cos,
        beams.sin,
        np.ascontiguousarray(real_ranges, dtype=np.float64),
        float(max_range),
        min_cos_incidence,
        scale_min,
        scale_max,
        prior,
        settings.iterations if iterations is None else iterations,
        settings.tolerance,
        settings.heading_tolerance,
        float(fit_distance),
        weights,
        real_sq,
        band,
        float(limit),
        float(accept_below) if area is not None else 0.0,
        *world.grid,
        out_pose,
        ranges,
        residuals,
        covariance,
    )
    share = fitted / n if n else 0.0
    return Refinement(
        out_pose, covariance if ok else None, float(sigma), ranges, residuals, share, int(casts),
        int(used), float(d_start), float(d_final), bool(gated),
    )  # fmt: skip
