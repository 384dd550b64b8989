"""The simulated robots' payloads: valid WIRE.md and ROS 2 messages of the plan's values, and
bad input that the service's decoders refuse."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas import InitialPose, LaserScan, Map, Odometry, Relocalize, SchemaError, decode
from service.ros2 import convert
from service.sim.plan import FleetSpec, Schedule, plan_fleet
from service.sim.wire import RANGE_DECIMALS, CdrWire, JsonWire, map_payload

SPEC = FleetSpec(robots=2, poses=6, beams=60, seed=3, map_id="m1")
PLAN = plan_fleet(SPEC)
STAMP = 1_732_300_000_000_000_000


def test_json_scans_and_odometry_are_the_plans() -> None:
    wire = JsonWire(PLAN)
    robot = PLAN.robots[1]
    for step in (1, 5, 7, 40):  # the way out, the way back, a later loop
        scan = decode(LaserScan, wire.scan(1, step, STAMP + step))
        assert scan.stamp_ns == STAMP + step
        want = robot.scans[robot.index(step)].ranges
        got = np.array([math.nan if r is None else r for r in scan.ranges])
        np.testing.assert_allclose(got, want, atol=0.5 * 10**-RANGE_DECIMALS, equal_nan=True)
        odom = decode(Odometry, wire.odometry(1, step, STAMP))
        assert (odom.x, odom.y, odom.theta) == robot.odometry_at(step)
    assert wire.key(1, "scan") == f"rlutf/robots/{robot.robot_id}/scan"


def test_json_start_map_and_relocalize() -> None:
    wire = JsonWire(PLAN)
    start = decode(InitialPose, wire.initial_pose(0, STAMP) or b"")
    assert (start.map_id, start.x) == ("m1", PLAN.robots[0].truth[0, 0])
    key, payload = wire.extra(0, "relocalize", STAMP)
    assert key.endswith("/relocalize") and decode(Relocalize, payload).map_id == "m1"
    assert decode(Map, map_payload(PLAN)).map_id == "m1"
    none = plan_fleet(FleetSpec(robots=1, poses=3, beams=8, initial_poses=False))
    assert JsonWire(none).initial_pose(0, STAMP) is None


@pytest.mark.parametrize("kind", ["malformed", "invalid"])
def test_json_bad_input_is_refused_by_the_schema(kind: str) -> None:
    key, payload = JsonWire(PLAN).extra(0, kind, STAMP)  # type: ignore[arg-type]
    assert key.endswith("/scan")
    with pytest.raises(SchemaError):
        decode(LaserScan, payload)


def test_cdr_payloads_are_the_json_robots_messages() -> None:
    json_wire, cdr = JsonWire(PLAN), CdrWire(PLAN)
    for step in (2, 8):
        a = decode(LaserScan, json_wire.scan(0, step, STAMP))
        b = convert.laser_scan(cdr.scan(0, step, STAMP))
        assert b.stamp_ns == STAMP
        got = np.array([math.nan if r is None else r for r in b.ranges])
        want = np.array([math.nan if r is None else r for r in a.ranges])
        np.testing.assert_allclose(got, want, atol=1e-4, equal_nan=True)  # float32 on ROS
        odom = convert.odometry(cdr.odometry(0, step, STAMP))
        assert (odom.x, odom.y) == pytest.approx(PLAN.robots[0].odometry_at(step)[:2])
    start = convert.initial_pose(cdr.initial_pose(0, STAMP) or b"", "m1")
    assert start.x == pytest.approx(PLAN.robots[0].truth[0, 0])
    assert cdr.key(0, "scan").startswith("0/r000/scan/sensor_msgs::msg::dds_::LaserScan_/")
    first, second = cdr.attachment(0), cdr.attachment(0)
    assert first is not None and second is not None and first[:8] != second[:8]


@pytest.mark.parametrize("kind", ["malformed", "invalid"])
def test_cdr_bad_input_is_refused(kind: str) -> None:
    _, payload = CdrWire(PLAN).extra(0, kind, STAMP)  # type: ignore[arg-type]
    with pytest.raises(SchemaError):
        convert.laser_scan(payload)


def test_ros_robots_cannot_ask_for_a_relocalization() -> None:
    spec = FleetSpec(robots=1, poses=3, beams=8, relocalize=Schedule(every=5))
    with pytest.raises(ValueError, match="relocalize"):
        CdrWire(plan_fleet(spec))
