import numpy as np

from rlutf.motion import relative
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)


def test_worlds_and_runs_are_reproducible_and_valid() -> None:
    a = make_building(np.random.default_rng(3))
    b = make_building(np.random.default_rng(3))
    assert a.geometry.equals(b.geometry)
    assert a.geometry.is_valid and len(a.segments) > 20
    rng = np.random.default_rng(1)
    path = make_trajectory(a, rng, 200)
    assert a.contains(path[:, :2]).all()
    steps = np.hypot(*np.diff(path[:, :2], axis=0).T)
    assert steps.max() <= 0.08 + 1e-9 and steps.sum() > 3.0


def test_scan_noise_dropout_and_people() -> None:
    world = make_building(np.random.default_rng(0))
    rng = np.random.default_rng(0)
    pose = make_trajectory(world, rng, 1)[0]
    clean = simulate_scan(world, pose, LidarModel(noise=0.0), rng)
    noisy = simulate_scan(world, pose, LidarModel(noise=0.02, dropout=0.2), rng)
    both = clean.valid() & noisy.valid()
    diff = noisy.ranges[both] - clean.ranges[both]
    assert 0.01 < float(np.std(diff)) < 0.03
    assert 0.1 < 1 - noisy.valid().mean() < 0.3
    person = pose[:2] + np.array([[1.0, 0.0]])
    blocked = simulate_scan(world, pose, LidarModel(noise=0.0), rng, people=person)
    assert np.nanmin(blocked.ranges) < np.nanmin(clean.ranges) or np.nanmin(clean.ranges) < 0.76


def test_odometry_drifts_but_follows_motion() -> None:
    world = make_building(np.random.default_rng(0))
    rng = np.random.default_rng(2)
    truth = make_trajectory(world, rng, 300)
    odom = drift_odometry(truth, OdometryModel(), rng)
    final_error = np.hypot(*(odom[-1, :2] - truth[-1, :2]))
    assert 0.01 < final_error < 2.0
    step = relative(odom[10], odom[11])
    true_step = relative(truth[10], truth[11])
    assert abs(step[0] - true_step[0]) < 0.02
