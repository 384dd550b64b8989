"""What one :meth:`rlutf.localizer.Localizer.update` returns."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rlutf.config import Status
from rlutf.mapchange import Returns
from rlutf.relocalize import Hypothesis

__all__ = ["LocalizeResult"]

FloatArray = NDArray[np.float64]


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
        hypotheses: while a relocalization cannot decide, the places the robot may be, best
            first (``pose`` is the first); empty otherwise.
        relocalizing: this update belongs to a relocalization (the map was searched or its
            hypotheses followed); the one where a hypothesis wins has status ``corrected``.
        score: the localization score in [0, 1] (:func:`rlutf.quality.localization_score`):
            under 0.5 when ``lost``.
        deviation_range: the radius around the position that holds the true one with 95 %
            probability, metres (:func:`rlutf.quality.deviation_range`); for a lost pose, the
            distance to the farthest corner of the map.
        returns: the scan's returns beside the ranges cast at ``pose`` (for map health,
            :mod:`rlutf.mapchange`); ``None`` when the update compared none.
        fit_needed: the share of the returns that had to fit for the pose to be trusted:
            ``min_fit``, or more for a robot whose scans usually fit better (its typical share
            less a margin); NaN where the update did not apply it (relocalizations).
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
    hypotheses: tuple[Hypothesis, ...] = ()
    relocalizing: bool = False
    score: float = 0.0
    deviation_range: float = math.inf
    returns: Returns | None = None
    fit_needed: float = math.nan
