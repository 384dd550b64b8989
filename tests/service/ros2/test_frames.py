"""Odometry in other frames than the settings name is taken, and said once per robot (and again
when its frames change): alone, and on a running service over real Zenoh sessions."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_client import RosListener, RosRobot, key, pose_of_tf
from service_harness import WORLD, Bench, Collector, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings
from service.ros2.frames import FRAME_CHARS, OdometryFrames

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF = "tf2_msgs/msg/TFMessage"


# ----------------------------------------------------------------------------------- alone
def test_another_odom_frame_is_said_once_and_again_when_it_changes() -> None:
    f = OdometryFrames("odom", "base_footprint")
    assert f.check("r1", "odom", "base_footprint", None) is None
    said = f.check("r1", "wheel_odom", "base_footprint", None)
    assert said is not None
    for part in ("r1", "'wheel_odom'", "not 'odom'", 'ros2.odom_frame = "wheel_odom"'):
        assert part in said, said
    assert f.check("r1", "wheel_odom", "base_footprint", None) is None  # said already
    assert f.check("r2", "wheel_odom", "base_footprint", None) is not None  # another robot
    changed = f.check("r1", "odom2", "base_footprint", None)
    assert changed is not None and "'odom2'" in changed
    assert f.check("r1", "odom", "base_footprint", None) is None  # right again: nothing
    assert f.check("r1", "odom2", "base_footprint", None) is not None  # wrong again: said
    f.forget("r2")
    assert f.check("r2", "wheel_odom", "base_footprint", None) is not None  # anew


def test_a_child_frame_is_said_only_when_tf_static_puts_it_elsewhere_in_the_plane() -> None:
    f = OdometryFrames("odom", "base_footprint")
    # base_link: unknown to tf_static, or above base_footprint (z is dropped): nothing to say
    assert f.check("r1", "odom", "base_link", None) is None
    assert f.check("r1", "odom", "base_link", (0.0, 0.0, 0.0)) is None
    assert f.check("r1", "odom", "base_link", (0.0, 0.0, math.tau)) is None
    # a child 20 cm ahead of the base: map -> odom is off by that
    said = f.check("r1", "odom", "base_link", (0.2, 0.0, 0.0))
    assert said is not None
    for part in ("r1", "'base_link'", "not 'base_footprint'", "x 0.200 m", "ros2.base_frame"):
        assert part in said, said
    assert f.check("r1", "odom", "base_link", (0.2, 0.0, 0.0)) is None
    both = f.check("r1", "wheel_odom", "base_link", (0.2, 0.0, 0.0))  # a change: all said
    assert both is not None and "ros2.odom_frame" in both and "ros2.base_frame" in both


def test_what_is_remembered_is_bounded_and_a_frame_id_is_quoted_safely() -> None:
    f = OdometryFrames("odom", "base_footprint", kept=3)
    for i in range(10):
        assert f.check(f"r{i}", "wheel_odom", "base_footprint", None) is not None
        assert len(f._said) <= 3
    said = f.check("forger", "x\nERROR forged line" + "y" * 10_000, "base_footprint", None)
    assert said is not None and "\n" not in said and "\\x0a" in said
    assert len(said) < 3 * FRAME_CHARS + 1000


# ---------------------------------------------------------------------------- on a service
@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1")) as b:
        yield b


def _robot(bench: Bench, ns: str, seed: int, **kw: Any) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 200)
    return RosRobot(ns, WORLD, truth, bench.client, False, np.zeros(3), rng=rng, **kw)


@pytest.mark.integration
def test_odometry_in_another_frame_is_taken_and_said_once_per_robot(
    bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    events = Collector()
    listener = RosListener()
    tf1 = key(0, "/robot1/tf", TF, False)
    subs = [
        bench.client.declare_subscriber("rlutf/robots/*/events", events),
        bench.client.declare_subscriber(key(0, "/robot1/amcl_pose", POSE, False), listener),
        bench.client.declare_subscriber(tf1, listener),
    ]
    laser = np.array([0.2, 0.0, 0.0])
    robots = [
        _robot(bench, "/robot1", 1, frames=("wheel_odom", "base_footprint")),
        # base_link over base_footprint (tf_static: no offset in the plane): nothing to say
        _robot(bench, "/robot2", 2, frames=("odom", "base_link"), laser=laser),
        # odometry of the laser, 20 cm ahead of the base: map -> odom is off by that
        _robot(bench, "/robot3", 3, frames=("odom", "laser"), laser=laser),
    ]
    bench.put_map()
    time.sleep(0.3)
    for r in robots[1:]:
        r.tf_static()
    time.sleep(0.3)

    def mismatches(robot: str) -> list[dict[str, Any]]:
        said = events.on(f"rlutf/robots/{robot}/events")
        return [e for e in said if e["code"] == "frame_mismatch"]

    with caplog.at_level(logging.WARNING):
        for r in robots:
            r.initial_pose()
        for _ in range(15):
            for r in robots:
                r.advance()
            time.sleep(0.03)
        # taken: robot1 is localized and its map -> odom goes out (for the frame set, 'odom')
        assert wait_until(lambda: len(listener.on(tf1)) >= 5)
        assert pose_of_tf(listener.on(tf1)[-1][0])[1:3] == ("map", "odom")
        assert wait_until(lambda: mismatches("robot1") and mismatches("robot3"))
        time.sleep(0.5)
        (e1,) = mismatches("robot1")  # once, for 16 Odometry messages
        assert e1["level"] == "warning" and e1["key"].startswith("0/robot1/odom/")
        assert "'wheel_odom'" in e1["message"] and "ros2.odom_frame" in e1["message"]
        (e3,) = mismatches("robot3")
        assert "'laser'" in e3["message"] and "ros2.base_frame" in e3["message"]
        assert mismatches("robot2") == []
        # the robot's frame changes: said again
        robots[0].frames = ("odom2", "base_footprint")
        robots[0].advance()
        assert wait_until(lambda: len(mismatches("robot1")) == 2)
        assert "'odom2'" in mismatches("robot1")[1]["message"]
    lines = [r.getMessage() for r in caplog.records if "frame_mismatch" in r.getMessage()]
    assert any("robot1" in line and "wheel_odom" in line for line in lines), lines
    for s in subs:
        s.undeclare()
