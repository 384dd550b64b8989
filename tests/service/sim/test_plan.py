"""The simulated fleet's plan: drawn the same from the same seed, looping without jumps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rlutf.motion import relative, wrap_angle
from rlutf.sim import OdometryModel
from service.sim.plan import FleetSpec, Schedule, plan_bytes, plan_fleet

NO_DRIFT = OdometryModel(trans_noise=0.0, rot_noise=0.0, rot_per_metre=0.0, heading_bias=0.0)
SPEC = FleetSpec(robots=2, poses=30, beams=90, seed=4)


@pytest.fixture(scope="module")
def plan():  # type: ignore[no-untyped-def]
    return plan_fleet(SPEC)


def test_the_same_spec_gives_the_same_plan_bit_for_bit(plan) -> None:  # type: ignore[no-untyped-def]
    again = plan_fleet(SPEC)
    assert again.world.to_geojson() == plan.world.to_geojson()
    for a, b in zip(plan.robots, again.robots, strict=True):
        assert a.robot_id == b.robot_id
        for name in ("truth", "odometry", "back", "initial"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        for sa, sb in zip(a.scans, b.scans, strict=True):
            np.testing.assert_array_equal(sa.ranges, sb.ranges)


def test_the_drawing_reports_each_robot_and_changes_nothing(plan) -> None:  # type: ignore[no-untyped-def]
    seen: list[int] = []
    again = plan_fleet(SPEC, on_robot=lambda: seen.append(1))
    assert len(seen) == SPEC.robots
    np.testing.assert_array_equal(again.robots[1].truth, plan.robots[1].truth)


def test_a_fleet_too_large_for_the_memory_is_named_before_it_is_drawn() -> None:
    from service.sim.fleet import memory_problem

    spec = FleetSpec(robots=1000, poses=201, beams=360)
    need = plan_bytes(spec)
    assert memory_problem(spec, available=2 * need) is None
    problem = memory_problem(spec, available=need)  # over half of what is available
    assert problem is not None
    assert "1000 robots with 201 poses of 360-beam scans" in problem
    assert f"{need / 1e9:.1f} GB" in problem
    # the estimate holds the plan and its JSON payloads: a drawn fleet takes less
    small = FleetSpec(robots=4, poses=50, beams=360, seed=1)
    drawn = plan_fleet(small)
    scan_bytes = sum(s.ranges.nbytes for r in drawn.robots for s in r.scans)
    assert scan_bytes < plan_bytes(small) < 4 * scan_bytes


def test_the_way_out_does_not_depend_on_the_way_back() -> None:
    with_drift = plan_fleet(SPEC)
    exact = plan_fleet(FleetSpec(robots=2, poses=30, beams=90, seed=4, odometry=None))
    # without drift no odometry is drawn, so the second robot's path comes from other draws
    assert not np.array_equal(with_drift.robots[1].truth, exact.robots[1].truth)
    # the first robot's path is drawn before any odometry, either way
    np.testing.assert_array_equal(with_drift.robots[0].truth, exact.robots[0].truth)


def test_a_robot_drives_out_and_back(plan) -> None:  # type: ignore[no-untyped-def]
    robot = plan.robots[0]
    n = len(robot.truth)
    assert [robot.index(k) for k in range(2 * n)] == [
        *range(n),
        *range(n - 2, 0, -1),
        0,
        1,
    ]


def test_odometry_without_drift_follows_the_truth_over_many_loops() -> None:
    plan = plan_fleet(FleetSpec(robots=1, poses=12, beams=8, seed=1, odometry=None))
    robot = plan.robots[0]
    for step in range(7 * len(robot.truth)):
        odom, truth = robot.odometry_at(step), robot.truth_at(step)
        assert odom[:2] == pytest.approx(tuple(truth[:2]), abs=1e-9)
        assert float(wrap_angle(odom[2] - truth[2])) == pytest.approx(0.0, abs=1e-9)


def test_drifting_odometry_is_continuous_and_keeps_drifting(plan) -> None:  # type: ignore[no-untyped-def]
    robot = plan.robots[0]
    n = 2 * len(robot.truth) - 2
    poses = np.array([robot.odometry_at(k) for k in range(5 * n + 1)])
    moves = relative(poses[:-1], poses[1:])
    truth = np.array([robot.truth_at(k) for k in range(5 * n + 1)])
    true_moves = relative(truth[:-1], truth[1:])
    # each step moves about as the robot did (drift is a few %), across the loops' ends too
    np.testing.assert_allclose(moves[:, :2], true_moves[:, :2], atol=0.02)
    # the way out reads what the plan holds, the way back its own draws
    np.testing.assert_array_equal(poses[: len(robot.truth)], robot.odometry)
    # each loop starts where the last one ended, so the drift does not snap back
    ends = {(round(x, 6), round(y, 6)) for x, y, _ in poses[::n]}
    assert len(ends) == 6


def test_a_long_run_is_as_cheap_as_a_short_one(plan) -> None:  # type: ignore[no-untyped-def]
    robot = plan.robots[0]
    n = 2 * len(robot.truth) - 2
    far = robot.odometry_at(1000 * n + 3)
    step = robot.odometry_at(3)
    # loop 1000 is loop 0 moved by the loops' drift: the same distance from the loop's start
    assert all(math.isfinite(v) for v in far)
    assert math.hypot(far[0] - step[0], far[1] - step[1]) > 0.0


def test_initial_poses_carry_the_offset_or_are_absent() -> None:
    offset = FleetSpec(robots=1, poses=5, beams=8, seed=2, initial_offset=(0.5, 0.0, 0.1))
    robot = plan_fleet(offset).robots[0]
    np.testing.assert_allclose(robot.initial, robot.truth[0] + [0.5, 0.0, 0.1])
    none = FleetSpec(robots=1, poses=5, beams=8, seed=2, initial_poses=False)
    assert plan_fleet(none).robots[0].initial is None


def test_schedules_say_what_is_due_at_each_step() -> None:
    spec = FleetSpec(
        robots=3,
        poses=5,
        beams=8,
        relocalize=Schedule(every=10, first=5, robots=(2,)),
        bad_input=Schedule(every=4, robots=(0, 1)),
    )
    plan = plan_fleet(spec)
    assert plan.extras(1) == [(0, "malformed"), (1, "malformed")]
    assert plan.extras(5) == [(2, "relocalize"), (0, "invalid"), (1, "invalid")]
    assert plan.extras(9) == [(0, "malformed"), (1, "malformed")]
    assert plan.extras(15) == [(2, "relocalize")]
    assert plan.extras(2) == []


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"robots": 0}, "robots"),
        ({"poses": 1}, "poses"),
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"robots": 2, "robot_ids": ("a",)}, "robot_ids"),
        ({"relocalize": Schedule(every=5, robots=(7,))}, "relocalize.robots"),
    ],
)
def test_a_bad_spec_names_the_field(kw: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        FleetSpec(**kw)  # type: ignore[arg-type]


def test_a_bad_schedule_names_the_field() -> None:
    with pytest.raises(ValueError, match="every"):
        Schedule(every=0)
    with pytest.raises(ValueError, match="first"):
        Schedule(every=1, first=0)


def test_a_fleet_far_too_large_is_named_in_a_short_line() -> None:
    # `rlutf simulate --path-seconds 1e300` (or --rate 1e300) printed the poses and the GB as
    # numbers of some 300 digits each
    from service.sim.fleet import memory_problem

    spec = FleetSpec(robots=5, poses=10**300, beams=360)
    problem = memory_problem(spec, available=24 * 10**9)
    assert problem is not None
    assert len(problem) < 250, problem
    assert "5 robots with 1e+300 poses of 360-beam scans" in problem
    assert "24.0 GB is available" in problem
