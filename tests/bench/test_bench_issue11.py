"""Issue 11's benchmark parts: new scenarios, made-up odometry, NEES, priors, targets."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import shapely

from bench.accuracy import ScenarioResult
from bench.carmen import ODOM5, slam_odometry
from bench.measures import Summary, nees, summarise
from bench.priors import NARROW, WIDE, sample_offsets, scans_to_converge
from bench.scenarios import Scenario, named_scenarios, simulate, world_of
from bench.speed import Point
from bench.tables import targets
from rlutf.motion import relative, wrap_angle
from rlutf.raycast import cast_rays
from rlutf.sim import make_trajectory


def _scenario(name: str, steps: int = 6) -> Scenario:
    return next(s for s in named_scenarios(steps) if s.name == name)


def test_range_4m_and_lidar_270_have_their_sensors() -> None:
    short = simulate(_scenario("range-4m"), 1)
    for scan in short.scans:
        assert len(scan.ranges) == 360 and scan.range_max == 4.0
        assert np.nanmax(scan.ranges) <= 4.0
    # The nominal sensor sees past 4 m from the same poses; the short one reports no return.
    nominal = simulate(_scenario("nominal"), 1)
    assert np.nanmax(nominal.scans[0].ranges) > 4.5
    assert np.isnan(short.scans[0].ranges).sum() > np.isnan(nominal.scans[0].ranges).sum()
    wide = simulate(_scenario("lidar-270"), 1)
    scan = wide.scans[0]
    assert len(scan.ranges) == 1080
    span = float(scan.angles[-1] - scan.angles[0])
    assert span == pytest.approx(1.5 * math.pi, rel=1e-9)
    assert math.degrees(float(np.diff(scan.angles).mean())) == pytest.approx(0.25, abs=0.001)


def test_noise_3cm_has_its_noise_and_dropouts() -> None:
    sc = _scenario("noise-3cm", steps=8)
    run = simulate(sc, 2)
    residuals, dropped, cast = [], 0, 0
    for pose, scan in zip(run.truth, run.scans, strict=True):
        clean = cast_rays(run.world, pose[None], scan.angles, sc.lidar.max_range)[0]
        # Beams a wall well inside the range: any no-return there is a dropout.
        seen = np.isfinite(clean) & (clean < sc.lidar.max_range - 0.2)
        cast += int(seen.sum())
        dropped += int(np.isnan(scan.ranges[seen]).sum())
        both = seen & np.isfinite(scan.ranges)
        residuals.append(scan.ranges[both] - clean[both])
    r = np.concatenate(residuals)
    assert float(np.std(r)) == pytest.approx(0.03, rel=0.1)
    assert abs(float(np.mean(r))) < 0.003
    assert dropped / cast == pytest.approx(0.10, abs=0.02)


def test_rooms_path_goes_through_doors() -> None:
    sc = _scenario("rooms", steps=300)
    map_id, world = world_of(sc, 1)
    assert map_id == "rooms-1"
    # Ten rooms and the corridor are one free space whose doors are its narrow necks.
    assert isinstance(world.geometry, shapely.Polygon)
    opened = world.geometry.buffer(-0.7).buffer(0.7)
    assert len(shapely.get_parts(opened)) == 1
    pieces = shapely.get_parts(world.geometry.buffer(-0.66))
    assert len(pieces) == 11
    path = make_trajectory(
        world, np.random.default_rng([1, 1]), 300, speed=sc.speed, clearance=sc.clearance
    )
    where = [
        next(i for i, p in enumerate(pieces) if p.buffer(0.7).contains(shapely.Point(q)))
        for q in path[:, :2]
    ]
    assert len(set(where)) >= 3  # a room, the corridor, another room


def test_odom5_increments_carry_the_stated_noise_and_bias() -> None:
    n = 4000
    steps = np.tile([0.1, 0.0, 0.05], (n, 1))
    truth = np.zeros((n + 1, 3))
    for i in range(n):
        c, s = math.cos(truth[i, 2]), math.sin(truth[i, 2])
        truth[i + 1] = truth[i] + [c * steps[i, 0], s * steps[i, 0], steps[i, 2]]
    truth[:, 2] = wrap_angle(truth[:, 2])
    odom = slam_odometry(truth)
    assert np.array_equal(odom, slam_odometry(truth))  # seeded
    d_odom = np.array([relative(odom[i], odom[i + 1]) for i in range(n)])
    d_true = np.array([relative(truth[i], truth[i + 1]) for i in range(n)])
    trans_rel = d_odom[:, 0] / d_true[:, 0] - 1.0
    assert float(np.std(trans_rel)) == pytest.approx(ODOM5.trans_noise, rel=0.1)
    assert abs(float(np.mean(trans_rel))) < 0.005
    dist = np.hypot(d_true[:, 0], d_true[:, 1])
    extra = wrap_angle(d_odom[:, 2] - d_true[:, 2])
    bias = extra / dist
    assert float(np.mean(bias)) == pytest.approx(0.02, abs=0.002)
    rot_rel = (extra - 0.02 * dist) / d_true[:, 2]
    assert float(np.std(rot_rel)) == pytest.approx(0.05, rel=0.1)


def test_nees_of_known_errors_and_covariances() -> None:
    truth = np.array([[0.0, 0.0, math.pi - 0.05], [1.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    poses = np.array([[0.1, 0.0, -math.pi + 0.05], [1.0, 2.2, 0.0], [0.0, 0.0, 0.0]])
    covs = np.stack(
        [
            np.diag([0.01, 1.0, 0.01]),
            np.array([[1.0, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 1.0]]),
            np.full((3, 3), np.nan),
        ]
    )
    got = nees(poses, truth, covs)
    # (0.1^2 / 0.01) + (0.1^2 / 0.01) after the heading wraps: 2; (0.2^2 / 0.04): 1; none.
    assert got[0] == pytest.approx(2.0)
    assert got[1] == pytest.approx(1.0)
    assert math.isnan(got[2])
    # A correlated covariance: e^T P^-1 e by hand.
    p = np.array([[0.02, 0.01, 0.0], [0.01, 0.02, 0.0], [0.0, 0.0, 0.001]])
    e = np.array([0.1, -0.05, 0.02])
    one = nees(e[None], np.zeros((1, 3)), p[None])[0]
    assert one == pytest.approx(float(e @ np.linalg.inv(p) @ e))
    s = summarise([poses], [truth], [("corrected",) * 3], [np.full(3, 0.001)], covariances=[covs])
    assert s.nees == pytest.approx(1.5) and s.nees_updates == 2
    assert s.max_error == pytest.approx(0.2)
    assert math.isnan(summarise([poses], [truth], [("x",) * 3], [np.ones(3)]).nees)


def test_prior_offsets_stay_in_bounds_and_are_seeded() -> None:
    narrow = sample_offsets(NARROW, 2000, seed=4)
    assert np.abs(narrow[:, :2]).max() <= 0.10
    assert np.abs(narrow[:, 2]).max() <= math.radians(3.0)
    # Uniform in the box: the corners are reached, not only a disc.
    assert np.hypot(narrow[:, 0], narrow[:, 1]).max() > 0.12
    wide = sample_offsets(WIDE, 2000, seed=4)
    length = np.hypot(wide[:, 0], wide[:, 1])
    assert length.max() <= 0.5 and length.max() > 0.48
    assert float(np.median(length)) == pytest.approx(0.25, abs=0.03)  # uniform length
    assert np.abs(wide[:, 2]).max() <= math.radians(15.0)
    assert np.abs(wide[:, 2]).max() > math.radians(14.0)
    assert np.array_equal(wide, sample_offsets(WIDE, 2000, seed=4))
    assert not np.array_equal(wide, sample_offsets(WIDE, 2000, seed=5))


def test_scans_to_converge() -> None:
    small = math.radians(0.5)
    assert scans_to_converge(np.array([0.01, 0.02]), np.array([small, small])) == 1
    assert scans_to_converge(np.array([0.3, 0.1, 0.01, 0.02]), np.full(4, small)) == 3
    # Within once, then out again: counts from the last time it left.
    assert scans_to_converge(np.array([0.01, 0.2, 0.01, 0.01]), np.full(4, small)) == 3
    assert scans_to_converge(np.array([0.01, 0.01]), np.array([small, 0.1])) is None


def _summary(**kw: float) -> Summary:
    base = {
        "updates": 100,
        "runs": 1,
        "rmse": 0.001,
        "heading_rmse": 0.001,
        "p95": 0.002,
        "within": 1.0,
        "diverged_runs": 0,
        "diverged_share": 0.0,
        "missing": 0,
        "lost": 0.0,
        "bound": 0.001,
        "median_ms": 0.2,
        "p99_ms": 0.4,
        "mean_ms": 0.2,
        "max_error": 0.004,
        "nees": 3.0,
        "nees_updates": 100,
    }
    base.update(kw)
    return Summary(**base)  # type: ignore[arg-type]


def _result(name: str, default: Summary, icp: Summary) -> ScenarioResult:
    return ScenarioResult(name, name, [], summaries={"default": default, "icp": icp})


def _met(rows: list[str], start: str) -> str:
    row = next(r for r in rows if r.startswith(f"| {start}"))
    return row.rsplit("|", 2)[1].strip()


def test_targets_say_yes_when_met_and_no_when_not() -> None:
    good = _summary()
    icp = _summary(rmse=0.002)
    speed = [Point("default", 360, "360 beams", 0.25, 0.5, 0.001)]
    maps = [Point("default", 20000, "aces (built from log)", 0.8, 1.5, 0.001)]
    rows = targets([_result("nominal", good, icp), _result("intel", good, icp)], speed, maps)
    for start in ("RMSE <= 1.5", "RMSE at most ICP's", "no divergence", "mean NEES", "median"):
        assert _met(rows, start) == "yes", start
    bad = replace(good, rmse=0.003, bound=0.001, max_error=0.7, nees=9.0)
    slow = [replace(speed[0], median_ms=0.5)]
    rows = targets([_result("nominal", bad, icp), _result("intel", good, icp)], slow, [])
    assert _met(rows, "RMSE <= 1.5") == "no"
    assert _met(rows, "RMSE at most ICP's on every simulated") == "no"
    assert _met(rows, "RMSE at most ICP's on every real") == "yes"
    assert _met(rows, "no divergence") == "no"
    assert _met(rows, "mean NEES") == "no"
    assert _met(rows, "median update <= 0.3") == "no"
    assert _met(rows, "median update <= 1") == "no"  # not measured is not met
    assert "3.00 x" in next(r for r in rows if r.startswith("| RMSE <= 1.5"))
