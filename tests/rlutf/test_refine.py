import math

import numpy as np
import pytest
from shapely.geometry import box

from rlutf import _lm
from rlutf.map import Map
from rlutf.motion import compose, wrap_angle
from rlutf.raycast import Beams, cast_rays
from rlutf.refine import RefineSettings, refine_pose
from rlutf.scan import Scan
from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan

SETTINGS = RefineSettings()


def _setup(seed: int, noise: float = 0.01) -> tuple[Map, np.ndarray, Scan, Beams]:
    rng = np.random.default_rng(seed)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 1)[0]
    scan = simulate_scan(world, truth, LidarModel(noise=noise), rng)
    return world, truth, scan, Beams.of(scan.angles).select(scan.valid())


def _refine(world: Map, start: np.ndarray, scan: Scan, beams: Beams, **kw: object):  # type: ignore[no-untyped-def]
    valid = scan.valid()
    return refine_pose(
        world, start, beams, scan.ranges[valid], scan.sensor_offset, scan.range_max, SETTINGS, **kw
    )


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noise_free_scan_converges_to_the_truth(seed: int) -> None:
    world, truth, scan, beams = _setup(seed, noise=0.0)
    start = truth + np.array([0.05, -0.04, math.radians(1.0)])
    fit = _refine(world, start, scan, beams)
    # The refinement ends on a step under its tolerance (1 mm), taken without a cast: its
    # error is of second order, far inside the tolerance.
    assert math.hypot(*(fit.pose[:2] - truth[:2])) < 0.01 * SETTINGS.tolerance
    assert abs(float(wrap_angle(fit.pose[2] - truth[2]))) < 0.02 * SETTINGS.heading_tolerance
    assert fit.casts <= SETTINGS.iterations
    # The ranges are those of the last cast, at most a step away: a beam that grazes a corner
    # may hit the wall beyond it there.
    assert fit.fit >= 1.0 - 2 / len(beams)


def test_the_last_small_step_is_taken_without_a_cast() -> None:
    world, truth, scan, beams = _setup(1, noise=0.0)
    start = truth + np.array([0.05, -0.04, math.radians(1.0)])
    checked = RefineSettings(tolerance=1e-9, heading_tolerance=1e-9)  # every step cast
    valid = scan.valid()
    args = (world, start, beams, scan.ranges[valid], scan.sensor_offset, scan.range_max)
    fit, slow = refine_pose(*args, SETTINGS), refine_pose(*args, checked)
    assert fit.casts < slow.casts
    assert math.hypot(*(fit.pose[:2] - slow.pose[:2])) < 0.01 * SETTINGS.tolerance


def test_one_iteration_only_evaluates_the_start() -> None:
    world, truth, scan, beams = _setup(4)
    start = truth + np.array([0.02, 0.0, 0.0])
    fit = _refine(world, start, scan, beams, iterations=1)
    np.testing.assert_array_equal(fit.pose, start)
    assert fit.casts == 1
    ranges = cast_rays(world, start, beams, scan.range_max)[0]
    np.testing.assert_array_equal(fit.ranges, ranges)


def test_range_jacobian_matches_finite_differences() -> None:
    world, truth, _, beams = _setup(5)
    offset = np.array([0.1, -0.05, 0.2])
    n = len(beams)
    ranges, residual, jac = np.empty(n), np.empty(n), np.zeros((n, 3))
    used = np.zeros(n, dtype=np.bool_)
    real = np.full(n, 5.0)
    _lm._linearise(
        *truth, offset, beams.cos, beams.sin, real, 30.0, 0.17, *world.grid,
        ranges, residual, jac, used,
    )  # fmt: skip
    h = 1e-6
    fd = np.empty((n, 3))
    smooth = np.ones(n, dtype=bool)
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        plus = cast_rays(world, compose(truth + step, offset), beams, 30.0)[0]
        minus = cast_rays(world, compose(truth - step, offset), beams, 30.0)[0]
        centre = cast_rays(world, compose(truth, offset), beams, 30.0)[0]
        fd[:, k] = (plus - minus) / (2 * h)
        # beams that jump to another wall within the step (corners) have no derivative
        smooth &= np.abs((plus - centre) - (centre - minus)) < 1e-9
    keep = used & smooth
    assert keep.sum() > 0.8 * n
    np.testing.assert_allclose(jac[keep], fd[keep], atol=2e-4, rtol=1e-4)


def test_covariance_is_calibrated() -> None:
    rng = np.random.default_rng(6)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 1)[0]
    nees, sigmas = [], []
    for _ in range(200):
        scan = simulate_scan(world, truth, LidarModel(noise=0.01), rng)
        beams = Beams.of(scan.angles).select(scan.valid())
        fit = _refine(world, truth + rng.normal(0, [0.01, 0.01, 0.005]), scan, beams)
        assert fit.covariance is not None
        e = fit.pose - truth
        e[2] = float(wrap_angle(e[2]))
        nees.append(float(e @ np.linalg.solve(fit.covariance, e)))
        sigmas.append(fit.sigma)
    # chi-square with 3 degrees of freedom: mean 3; the mean of 200 has a spread of 0.17
    assert 2.4 < np.mean(nees) < 3.6
    assert np.median(sigmas) == pytest.approx(0.01, rel=0.15)


def test_clutter_is_down_weighted() -> None:
    world, truth, scan, _ = _setup(7)
    rng = np.random.default_rng(7)
    ranges = scan.ranges.copy()
    clutter = rng.random(len(ranges)) < 0.3
    ranges[clutter] *= rng.uniform(0.2, 0.8, int(clutter.sum()))  # people, boxes: short
    cluttered = Scan.create(
        ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
    )
    beams = Beams.of(cluttered.angles).select(cluttered.valid())
    fit = _refine(world, truth + np.array([0.03, 0.02, 0.01]), cluttered, beams)
    assert math.hypot(*(fit.pose[:2] - truth[:2])) < 0.003
    assert fit.fit < 0.8  # the clutter does not fit, and says so


def test_a_corridor_axis_keeps_the_prior_and_says_so() -> None:
    world = Map.from_shapely(box(0.0, 0.0, 60.0, 1.6))
    truth = np.array([30.0, 0.8, 0.0])
    lidar = LidarModel(max_range=4.0, noise=0.005)
    scan = simulate_scan(world, truth, lidar, np.random.default_rng(8))
    beams = Beams.of(scan.angles).select(scan.valid())
    start = truth + np.array([0.05, 0.02, 0.01])
    fit = _refine(world, start, scan, beams)
    assert fit.covariance is not None
    # across the corridor and in heading: corrected and certain
    assert abs(fit.pose[1] - truth[1]) < 0.002
    assert math.sqrt(fit.covariance[1, 1]) < 0.003
    # along it: nothing to go by; the start is kept and the covariance says so
    assert abs(fit.pose[0] - start[0]) < 0.01
    assert math.sqrt(fit.covariance[0, 0]) > 0.3
