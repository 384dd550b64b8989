"""A live ROS 2 robot whose LaserScans say ``range_max: inf`` is localized by ``rlutf serve
--ros2``: every such scan was refused with an Event (the wire contract's range_max is finite)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, RosListener, RosRobot, key, scan_msg
from service_harness import WORLD, Bench, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings

pytestmark = pytest.mark.integration

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"


class UnlimitedRobot(RosRobot):
    """A robot whose driver says "no limit": range_max +inf, no return as +inf (REP 117)."""

    def advance(self) -> int:
        self.step += 1
        self.odom(self.step)
        msg = scan_msg(self.world, self.truth[self.step], self.stamp(self.step), self.rng)
        msg.ranges = np.where(np.isnan(msg.ranges), np.float32(np.inf), msg.ranges)
        msg.range_max = math.inf
        self.put("scan", "sensor_msgs/msg/LaserScan", msg)
        return self.step


@pytest.fixture
def ros_bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1")) as b:
        yield b


def test_scans_with_an_infinite_range_max_are_localized_live(ros_bench: Bench) -> None:
    bench = ros_bench
    rng = np.random.default_rng(4)
    truth = make_trajectory(WORLD, rng, 60)
    r = UnlimitedRobot(
        "/robot1", WORLD, truth, bench.client, False, np.array([1.0, -0.5, 0.3]), rng=rng
    )
    listener = RosListener()
    pose_key = key(0, "/robot1/amcl_pose", POSE, False)
    sub = bench.client.declare_subscriber(pose_key, listener)
    bench.put_map()
    time.sleep(0.3)
    r.initial_pose()
    time.sleep(0.5)
    for _ in range(20):
        r.advance()
        time.sleep(0.03)
    assert wait_until(lambda: len(listener.on(pose_key)) >= 15), len(listener.on(pose_key))
    for raw, _ in listener.on(pose_key)[-5:]:
        m = TS.deserialize_cdr(raw, POSE)
        i = round((m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec - r.t0) / 1e8)
        p = m.pose.pose.position
        assert math.hypot(p.x - truth[i, 0], p.y - truth[i, 1]) < 0.05
    sub.undeclare()
