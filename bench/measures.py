"""Accuracy and speed measures of a method over runs (DESIGN.md, "How we measure").

Errors are taken per update against the reference pose. Several runs of one scenario are
pooled: RMSE over all their updates, divergences counted per run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bench.scenarios import FloatArray
from rlutf.motion import wrap_angle

#: An update whose position error is over this has diverged, metres.
DIVERGED = 0.5
#: An update is "within" when its errors are under both of these (metres, radians).
WITHIN_M = 0.05
WITHIN_RAD = math.radians(2.0)


def errors(poses: FloatArray, truth: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-update position error (metres) and absolute heading error (radians).

    Args:
        poses: ``(U, 3)`` estimates; rows with NaN are missing.
        truth: ``(U, 3)`` reference poses.

    Returns:
        ``(U,)`` and ``(U,)``; NaN where the estimate is missing.
    """
    trans = np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1])
    heading = np.abs(wrap_angle(poses[:, 2] - truth[:, 2]))
    return np.asarray(trans, dtype=np.float64), np.asarray(heading, dtype=np.float64)


@dataclass(frozen=True)
class Summary:
    """One method on one scenario (all its runs pooled).

    Attributes:
        updates: updates graded.
        runs: runs pooled.
        rmse: translation RMSE, metres.
        heading_rmse: heading RMSE, radians.
        p95: 95th percentile of the translation error, metres.
        within: share of updates within 5 cm and 2 degrees.
        diverged_runs: runs with any update over :data:`DIVERGED`.
        diverged_share: share of updates over :data:`DIVERGED`.
        missing: updates without a pose.
        lost: share of updates whose status was ``lost``.
        bound: RMS over the updates of the per-scan Cramer-Rao bound, metres (NaN if none).
        median_ms: median update latency, milliseconds.
        p99_ms: 99th percentile update latency, milliseconds.
        mean_ms: mean update latency (CPU per scan), milliseconds.
        max_error: largest position error of any update, metres.
        nees: mean normalised estimation error squared over the updates with a covariance
            (NaN for a method that gives none); 3 for a consistent covariance.
        nees_updates: updates the NEES is taken over.
    """

    updates: int
    runs: int
    rmse: float
    heading_rmse: float
    p95: float
    within: float
    diverged_runs: int
    diverged_share: float
    missing: int
    lost: float
    bound: float
    median_ms: float
    p99_ms: float
    mean_ms: float
    max_error: float = math.nan
    nees: float = math.nan
    nees_updates: int = 0

    @property
    def ratio(self) -> float:
        """Translation RMSE over the bound (NaN without a bound)."""
        return self.rmse / self.bound if self.bound > 0 else math.nan


def nees(poses: FloatArray, truth: FloatArray, covariances: FloatArray) -> FloatArray:
    """Per-update normalised estimation error squared ``e^T P^-1 e``.

    ``e = (dx, dy, wrap(dtheta))`` is the estimate minus the truth and ``P`` its ``(3, 3)``
    covariance. For an unbiased estimator with a consistent covariance it is chi-square
    distributed with 3 degrees of freedom (mean 3).

    Args:
        poses: ``(U, 3)`` estimates.
        truth: ``(U, 3)`` reference poses.
        covariances: ``(U, 3, 3)``; NaN (or singular) where there is none.

    Returns:
        ``(U,)``; NaN where the pose or covariance is missing or singular.
    """
    e = np.asarray(poses, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    e[:, 2] = wrap_angle(e[:, 2])
    cov = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    out = np.full(len(e), math.nan)
    ok = np.isfinite(e).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
    for i in np.nonzero(ok)[0]:
        try:
            out[i] = float(e[i] @ np.linalg.solve(cov[i], e[i]))
        except np.linalg.LinAlgError:
            continue
    return out


def rms(values: FloatArray) -> float:
    """Root mean square of the finite values (NaN if none)."""
    v = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(v * v))) if len(v) else math.nan


def summarise(
    poses: Sequence[FloatArray],
    truths: Sequence[FloatArray],
    statuses: Sequence[Sequence[str]],
    seconds: Sequence[FloatArray],
    bounds: Sequence[FloatArray] | None = None,
    covariances: Sequence[FloatArray | None] | None = None,
) -> Summary:
    """Pool the runs of one method on one scenario.

    Args:
        poses: per run, ``(U, 3)`` estimates.
        truths: per run, ``(U, 3)`` reference poses.
        statuses: per run, the status of each update.
        seconds: per run, ``(U,)`` update latencies.
        bounds: per run, ``(U,)`` per-scan bounds (optional).
        covariances: per run, ``(U, 3, 3)`` covariances or ``None`` (optional): the NEES.
    """
    trans_all, head_all = [], []
    diverged = 0
    missing = 0
    for p, t in zip(poses, truths, strict=True):
        tr, hd = errors(p, t)
        trans_all.append(tr)
        head_all.append(hd)
        missing += int(np.isnan(tr).sum())
        diverged += int(bool(np.any(tr[np.isfinite(tr)] > DIVERGED)))
    trans = np.concatenate(trans_all)
    head = np.concatenate(head_all)
    graded = np.isfinite(trans)
    ok = graded & (trans <= WITHIN_M) & (head <= WITHIN_RAD)
    status = [s for run in statuses for s in run]
    ms = np.concatenate(list(seconds)) * 1e3
    bound = math.nan
    if bounds is not None:
        bound = rms(np.concatenate(list(bounds)))
    scores = [
        nees(p, t, c)
        for p, t, c in zip(poses, truths, covariances or [None] * len(poses), strict=True)
        if c is not None
    ]
    graded_nees = np.concatenate(scores) if scores else np.empty(0)
    graded_nees = graded_nees[np.isfinite(graded_nees)]
    return Summary(
        updates=len(trans),
        runs=len(poses),
        rmse=rms(trans),
        heading_rmse=rms(head),
        p95=float(np.percentile(trans[graded], 95)) if graded.any() else math.nan,
        within=float(ok.sum() / len(trans)) if len(trans) else math.nan,
        diverged_runs=diverged,
        diverged_share=float(np.mean(trans[graded] > DIVERGED)) if graded.any() else math.nan,
        missing=missing,
        lost=float(np.mean([s == "lost" for s in status])) if status else math.nan,
        bound=bound,
        median_ms=float(np.median(ms)),
        p99_ms=float(np.percentile(ms, 99)),
        mean_ms=float(np.mean(ms)),
        max_error=float(np.max(trans[graded])) if graded.any() else math.nan,
        nees=float(np.mean(graded_nees)) if len(graded_nees) else math.nan,
        nees_updates=len(graded_nees),
    )


def fit_power(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """Least-squares fit of ``y = a * x**b`` on log-log axes; returns ``(a, b)``."""
    lx, ly = np.log(np.asarray(x, dtype=np.float64)), np.log(np.asarray(y, dtype=np.float64))
    b, log_a = np.polyfit(lx, ly, 1)
    return float(math.exp(log_a)), float(b)
