import numpy as np
import shapely

from rlutf import sim
from rlutf.map import Map
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


def test_long_paths_keep_moving_with_their_clearance() -> None:
    # The old path stalled after about 220 steps: bent legs left the waypoint out of sight.
    import shapely

    steps, dt, speed, clearance = 2000, 0.1, 0.8, 0.45
    for seed, (w, h, rx, ry) in ((1, (18.0, 12.0, 2, 2)), (3, (24.0, 14.0, 3, 2))):
        world = make_building(np.random.default_rng(seed), w, h, rx, ry)
        path = make_trajectory(
            world, np.random.default_rng([seed, 1]), steps, dt=dt, speed=speed, clearance=clearance
        )
        moved = np.hypot(*np.diff(path[:, :2], axis=0).T)
        assert moved.sum() >= 0.8 * speed * dt * steps
        # Still moving at the end: no stall in the last quarter.
        assert moved[-steps // 4 :].sum() >= 0.5 * speed * dt * steps / 4
        inner = world.geometry.buffer(-clearance + 1e-6)
        assert shapely.contains_xy(inner, path[:, 0], path[:, 1]).all()


def test_the_free_space_with_clearance_is_made_once_per_map() -> None:
    # A site's map with thousands of obstacles takes seconds to buffer: every robot, person
    # and path drawn on one map shares one, and draws what it drew before the sharing.
    rng = np.random.default_rng(3)
    world = make_building(rng)
    again = Map.from_shapely(world.geometry)
    first = make_trajectory(world, np.random.default_rng(5), 120)
    assert sim._inner(world, 0.45) is sim._inner(world, 0.45)
    assert sim._inner(world, 0.5) is not sim._inner(world, 0.45)
    # the cached free space draws what a fresh one does
    second = make_trajectory(world, np.random.default_rng(5), 120)
    fresh = make_trajectory(again, np.random.default_rng(5), 120)
    assert np.array_equal(first, second) and np.array_equal(first, fresh)
    inner = world.geometry.buffer(-0.45)
    assert shapely.equals_exact(sim._inner(world, 0.45), inner, 0.0)
