"""Accuracy measures: RMSE, percentiles, shares, divergences, missing poses, power fits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.measures import errors, fit_power, summarise


def test_summary_of_known_errors() -> None:
    truth = np.zeros((4, 3))
    a = np.array(
        [
            [0.03, 0.03, 0.0],
            [0.0, 0.0, math.radians(3.0)],
            [0.0, 0.0, 0.0],
            [np.nan, np.nan, np.nan],
        ]
    )
    b = np.array([[0.6, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2 * math.pi], [0.0, 0.0, 0.0]])
    s = summarise(
        [a, b],
        [truth, truth],
        [("corrected", "corrected", "tracking", "lost"), ("lost",) * 4],
        [np.full(4, 0.001), np.full(4, 0.003)],
        [np.full(4, 0.002), np.full(4, 0.002)],
    )
    trans = np.array([math.hypot(0.03, 0.03), 0.0, 0.0, 0.6, 0.0, 0.0, 0.0])
    assert s.updates == 8 and s.runs == 2 and s.missing == 1
    assert s.rmse == pytest.approx(math.sqrt(np.mean(trans**2)))
    assert s.heading_rmse == pytest.approx(math.radians(3.0) / math.sqrt(7))
    assert s.p95 == pytest.approx(np.percentile(trans, 95))
    # Within 5 cm and 2 degrees: a[0], a[2], b[1], b[2] (2 pi wraps to 0), b[3].
    assert s.within == pytest.approx(5 / 8)
    assert s.diverged_runs == 1 and s.diverged_share == pytest.approx(1 / 7)
    assert s.lost == pytest.approx(5 / 8)
    assert s.bound == pytest.approx(0.002) and s.ratio == pytest.approx(s.rmse / 0.002)
    assert s.median_ms == pytest.approx(2.0) and s.mean_ms == pytest.approx(2.0)


def test_errors_wrap_heading() -> None:
    trans, head = errors(np.array([[1.0, 1.0, math.pi - 0.01]]), np.array([[1.0, 2.0, -math.pi]]))
    assert trans[0] == pytest.approx(1.0) and head[0] == pytest.approx(0.01)


def test_power_fit_recovers_exponent() -> None:
    x = np.array([90.0, 180.0, 360.0, 720.0, 1440.0])
    a, b = fit_power(x, 0.02 * x**0.8)
    assert a == pytest.approx(0.02) and b == pytest.approx(0.8)
