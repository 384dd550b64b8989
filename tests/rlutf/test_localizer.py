import math

import numpy as np
import pytest

from rlutf.errors import ConfigError
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.motion import compose, relative, wrap_angle
from rlutf.scan import Scan
from rlutf.sim import LidarModel, make_building, make_trajectory, simulate_scan

STEPS = 80


def _run(config: LocalizerConfig, seed: int, steps: int = STEPS) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    world = make_building(rng)
    truth = make_trajectory(world, rng, steps)
    # Injected error: 20 cm in a direction that depends on the seed, and 5 degrees.
    start = compose(truth[0], [0.2 * math.cos(seed), 0.2 * math.sin(seed), math.radians(5)])
    loc = Localizer(world, start, config, seed=seed)
    poses = [start]
    for i in range(1, steps):
        scan = simulate_scan(world, truth[i], LidarModel(), rng)
        res = loc.update(relative(truth[i - 1], truth[i]), scan)
        assert world.contains(res.pose[None, :2])[0], "pose left the free space"
        poses.append(res.pose)
    return np.array(poses), truth


def _final_error(poses: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    e = poses[-1] - truth[-1]
    return math.hypot(e[0], e[1]), abs(math.degrees(float(wrap_angle(e[2]))))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_default_mode_removes_injected_error(seed: int) -> None:
    poses, truth = _run(LocalizerConfig(), seed)
    trans, deg = _final_error(poses, truth)
    assert trans < 0.04 and deg < 0.6, (trans, deg)
    # and it stays corrected over the last part of the run
    err = np.hypot(*(poses[-20:, :2] - truth[-20:, :2]).T)
    assert err.max() < 0.06


@pytest.mark.parametrize("seed", [0, 1])
def test_paper_mode_removes_injected_error(seed: int) -> None:
    poses, truth = _run(LocalizerConfig.paper(), seed)
    trans, deg = _final_error(poses, truth)
    # The paper's search keeps no elite and so wanders more; it still removes most of it.
    assert trans < 0.1 and deg < 1.5, (trans, deg)


def test_same_seed_same_poses_bit_for_bit() -> None:
    a, _ = _run(LocalizerConfig(), 5, steps=25)
    b, _ = _run(LocalizerConfig(), 5, steps=25)
    assert a.tobytes() == b.tobytes()
    c, _ = _run(LocalizerConfig(seed=99), 5, steps=25)
    assert a.tobytes() != c.tobytes()


def test_empty_scan_and_no_returns_are_lost_without_exception() -> None:
    rng = np.random.default_rng(0)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 2)
    loc = Localizer(world, truth[0])
    no_returns = Scan.create([None] * 360, -math.pi, 2 * math.pi / 360, 0.05, 12.0)
    res = loc.update(relative(truth[0], truth[1]), no_returns)
    assert res.status == "lost" and math.isinf(res.discrepancy)
    np.testing.assert_allclose(res.pose, truth[1], atol=1e-9)  # dead reckoning
    empty = Scan.create(np.zeros(0), -math.pi, 0.1, 0.05, 12.0)
    assert loc.update([0.0, 0.0, 0.0], empty).status == "lost"


def test_tracking_without_error_accepts_the_prediction() -> None:
    rng = np.random.default_rng(4)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 10)
    loc = Localizer(world, truth[0])
    lidar = LidarModel(noise=0.0)
    statuses = []
    for i in range(1, 10):
        res = loc.update(
            relative(truth[i - 1], truth[i]), simulate_scan(world, truth[i], lidar, rng)
        )
        statuses.append(res.status)
        assert res.iterations == 0 or res.status != "tracking"
    assert statuses.count("tracking") == len(statuses)


def test_partial_field_of_view_with_sensor_offset() -> None:
    rng = np.random.default_rng(7)
    world = make_building(rng)
    truth = make_trajectory(world, rng, 40)
    lidar = LidarModel(beams=181, fov=math.pi)
    offset = np.array([0.0, 0.0, 0.0])
    loc = Localizer(world, compose(truth[0], [0.1, -0.05, 0.03]))
    for i in range(1, 40):
        scan = simulate_scan(world, truth[i], lidar, rng)
        scan = Scan.create(
            scan.ranges,
            scan.angle_min,
            scan.angle_increment,
            scan.range_min,
            scan.range_max,
            offset,
        )
        res = loc.update(relative(truth[i - 1], truth[i]), scan)
    assert math.hypot(*(res.pose[:2] - truth[-1][:2])) < 0.06


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"epsilon": 0.0}, "epsilon"),
        ({"candidates": 0}, "candidates"),
        ({"delta": float("nan")}, "delta"),
        ({"mode": "fast"}, "mode"),
        ({"discrepancy": "icp"}, "discrepancy"),
        ({"epsilon": 0.5, "lost_threshold": 0.1}, "lost_threshold"),
    ],
)
def test_config_is_validated(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        LocalizerConfig(**kwargs)
