"""The pose quality fields: the 95 % range of a covariance, the score, and the localizer's use."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rlutf.localizer import Localizer
from rlutf.motion import compose, relative
from rlutf.quality import (
    LOST_SCORE,
    coverage_factor,
    deviation_range,
    farthest_on_map,
    localization_score,
)
from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan

unit = st.floats(0.0, 1.0)


def kidnap_path(world, seed: int, steps: int, at: int) -> tuple[np.ndarray, np.ndarray]:
    """``(truth, odometry)``: at scan ``at`` the robot is carried to a random place (a new path
    from there) while its odometry goes on as if it had not been (exact odometry)."""
    before = make_trajectory(world, np.random.default_rng([seed, 1]), at + 1)
    after = make_trajectory(world, np.random.default_rng([seed, 7]), steps - at)
    truth = np.vstack([before[:at], after])
    odometry = truth.copy()
    for i in range(1, steps):
        step = relative(truth[i - 1], truth[i]) if i != at else relative(before[at - 1], before[at])
        odometry[i] = compose(odometry[i - 1], step)
    return truth, odometry


def _covariance(sx: float, sy: float, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    cov = np.eye(3) * 1e-4
    cov[:2, :2] = rot @ np.diag([sx * sx, sy * sy]) @ rot.T
    return cov


def test_coverage_factor_is_the_known_quantile_at_both_ends() -> None:
    # a circle: the chi-square quantile of 2 dof; a line: the normal's 97.5 % point
    assert coverage_factor(1.0) == pytest.approx(math.sqrt(-2.0 * math.log(0.05)), rel=1e-6)
    assert coverage_factor(0.0) == pytest.approx(1.959964, rel=1e-5)
    assert coverage_factor(0.3) < coverage_factor(0.6) < coverage_factor(0.9)


@pytest.mark.parametrize(("sx", "sy"), [(0.01, 0.01), (0.05, 0.01), (0.2, 0.002), (0.03, 0.02)])
def test_the_range_holds_95_percent_of_gaussian_errors(sx: float, sy: float) -> None:
    rng = np.random.default_rng(7)
    cov = _covariance(sx, sy, 0.7)
    r = deviation_range(cov, math.inf)
    errors = rng.multivariate_normal(np.zeros(2), cov[:2, :2], size=200_000)
    inside = float(np.mean(np.hypot(errors[:, 0], errors[:, 1]) <= r))
    assert inside == pytest.approx(0.95, abs=0.003)


@given(st.floats(1e-4, 1.0), st.floats(1e-4, 1.0), st.floats(-math.pi, math.pi))
@settings(max_examples=100, deadline=None)
def test_the_range_does_not_depend_on_the_axes(sx: float, sy: float, angle: float) -> None:
    a = deviation_range(_covariance(sx, sy, angle), math.inf)
    b = deviation_range(_covariance(sx, sy, 0.0), math.inf)
    assert a == pytest.approx(b, rel=1e-6)
    assert 1.959 * max(sx, sy) <= a <= 2.448 * max(sx, sy)


def test_no_covariance_gives_the_fallback() -> None:
    assert deviation_range(None, 12.5) == 12.5
    assert deviation_range(np.full((3, 3), math.nan), 3.0) == 3.0
    assert farthest_on_map(1.0, 1.0, (0.0, 0.0, 10.0, 5.0)) == pytest.approx(math.hypot(9, 4))


@given(unit, st.floats(0.05, 1.0), unit, st.floats(0.0, 100.0))
def test_a_lost_pose_scores_under_one_half(fit: float, floor: float, typical: float, dev: float):
    s = localization_score(fit, floor, typical, dev, True, 0.5)
    assert 0.0 <= s <= LOST_SCORE < 0.5


@given(unit, unit, unit, st.floats(0.0, 100.0))
def test_the_score_is_in_unit_range(fit: float, floor: float, typical: float, dev: float) -> None:
    assert 0.0 <= localization_score(fit, floor, typical, dev, False, 0.5) <= 1.0


def test_the_score_follows_the_fit_and_the_range() -> None:
    # as good as usual and well determined: 1; at the floor: a half
    assert localization_score(0.97, 0.72, 0.97, 0.0, False, 0.5) == 1.0
    assert localization_score(0.72, 0.72, 0.97, 0.0, False, 0.5) == pytest.approx(0.5)
    mid = localization_score(0.85, 0.72, 0.97, 0.0, False, 0.5)
    assert 0.5 < mid < 1.0
    # the range halves it at `determined`, and a pose known nowhere scores nothing
    assert localization_score(0.97, 0.72, 0.97, 0.5, False, 0.5) == pytest.approx(0.5)
    assert localization_score(0.97, 0.72, 0.97, math.inf, False, 0.5) == 0.0
    assert localization_score(math.nan, 0.72, 0.97, 0.01, False, 0.5) == 0.0


def test_poses_carry_a_small_range_and_a_high_score_while_tracking() -> None:
    world = make_building(np.random.default_rng(3))
    truth, odometry = kidnap_path(world, 3, 40, 39)
    rng = np.random.default_rng(4)
    loc = Localizer(world, truth[0], seed=3)
    for k in range(1, 30):
        res = loc.update(
            relative(odometry[k - 1], odometry[k]),
            simulate_scan(world, truth[k], LidarModel(), rng),
        )
        assert res.status != "lost"
        assert 0.0 < res.deviation_range < 0.02 and res.score > 0.8


@pytest.mark.parametrize("seed", [1, 2])
def test_a_kidnapped_robot_scores_low_within_three_scans_and_recovers(seed: int) -> None:
    world = make_building(np.random.default_rng(seed))
    truth, odometry = kidnap_path(world, seed, 60, 25)
    rng = np.random.default_rng([seed, 3])
    loc = Localizer(world, truth[0], seed=seed)
    scores, errors, ranges, statuses = [], [], [], []
    for k in range(1, 60):
        scan = simulate_scan(world, truth[k], LidarModel(), rng)
        res = loc.update(relative(odometry[k - 1], odometry[k]), scan)
        scores.append(res.score)
        errors.append(math.hypot(*(res.pose[:2] - truth[k, :2])))
        ranges.append(res.deviation_range)
        statuses.append(res.status)
        if res.status == "lost":
            assert res.score < 0.5
    after = slice(24, 24 + 3)  # update k is index k - 1; the kidnap is at scan 25
    assert min(scores[after]) < 0.5, scores[20:35]
    # found again: the last poses are right, score high, range small and covering the truth
    assert max(errors[-10:]) < 0.05 and min(scores[-10:]) > 0.8
    assert all(e <= r for e, r in zip(errors[24:], ranges[24:], strict=True) if r > 1.0)
