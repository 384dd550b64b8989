"""Odometry read from tf (``ros2.odom_source = "tf"``) that is on tf under other frames than the
settings name is not found: said once per robot (and again when it sees other frames), alone
and on a running service over real Zenoh sessions."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ros_client import RosListener, RosRobot, drive, key, others_transforms
from service_harness import WORLD, Bench, Collector, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings
from service.ros2.frames import FRAME_CHARS, TfOdometryFrames

TF = "tf2_msgs/msg/TFMessage"
S = 1_000_000_000


def _frames(**kw: Any) -> TfOdometryFrames:
    return TfOdometryFrames("map", "odom", "base_footprint", 2 * S, **kw)


# ----------------------------------------------------------------------------------- alone
def test_tf_without_the_odometry_is_said_after_the_wait_and_once() -> None:
    f = _frames()
    seen = [("odom", "base_link"), ("base_link", "laser")]
    assert f.check("r1", False, seen, 0) is None  # odometry may come in the next message
    assert f.check("r1", False, seen, 1 * S) is None
    said = f.check("r1", False, seen, 2 * S)
    assert said is not None
    for part in (
        "r1",
        "odom -> base_link, base_link -> laser",  # the frames seen
        "no odom -> base_footprint",  # the frames expected
        "ros2.odom_frame",
        "ros2.base_frame",
        'set ros2.base_frame = "base_link"',  # the setting that fits what is seen
        'ros2.odom_source = "odom"',
        "no map -> odom",
    ):
        assert part in said, said
    assert f.check("r1", False, seen, 3 * S) is None  # said already
    assert f.check("r1", False, seen[1:], 4 * S) is None  # nothing new seen
    again = f.check("r1", False, [("wheel_odom", "base_footprint")], 5 * S)
    assert again is not None and 'set ros2.odom_frame = "wheel_odom"' in again
    # the odometry found: forgotten, and a robot that loses it again is said again
    assert f.check("r1", True, [("odom", "base_footprint")], 6 * S) is None
    assert f.check("r1", False, seen, 7 * S) is None
    assert f.check("r1", False, seen, 9 * S) is not None


def test_a_robots_odometry_between_its_other_transforms_is_not_said() -> None:
    f = _frames()
    for i in range(50):  # links at 10 Hz, the odometry at 1 Hz in messages of its own
        found = i % 10 == 0
        pairs = [("odom", "base_footprint")] if found else [("base_link", "wheel")]
        assert f.check("r1", found, pairs, i * S // 10) is None


def test_only_map_to_odom_is_not_the_robots_tf() -> None:
    f = _frames()
    # the map -> odom the service (or an AMCL beside it) publishes on the robot's tf
    for i in range(5):
        assert f.check("r1", False, [("map", "odom")], i * S) is None
    said = f.check("r1", False, [("map", "odom"), ("odom", "base_link")], 10 * S)
    assert said is None  # the robot's own transform starts the wait
    said = f.check("r1", False, [("odom", "base_link")], 12 * S)
    assert said is not None and "map -> odom" not in said.split("no map -> odom")[0]


def test_what_is_remembered_is_bounded_and_frames_are_quoted_safely() -> None:
    f = _frames(kept=3, pairs_kept=4)
    for i in range(10):
        f.check(f"r{i}", False, [("a", "b")], 0)
        assert len(f._missing) <= 3
    many = [(f"p{i}", f"c{i}") for i in range(100)]
    f.check("many", False, many, 0)
    said = f.check("many", False, many, 2 * S)
    assert said is not None and "p3 -> c3" in said and "p4" not in said
    forged = [("x\nERROR forged line" + "y" * 10_000, "base_footprint")]
    f.check("forger", False, forged, 0)
    said = f.check("forger", False, forged, 2 * S)
    assert said is not None and "\n" not in said and "\\x0a" in said
    assert len(said) < 4 * FRAME_CHARS + 2000


# ---------------------------------------------------------------------------- on a service
@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    ros2 = Ros2Settings(enabled=True, map_id="m1", odom_source="tf")
    with running_bench(tmp_path, ros2=ros2) as b:
        yield b


def _robot(bench: Bench, ns: str, seed: int, frames: tuple[str, str]) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 200)
    return RosRobot(
        ns, WORLD, truth, bench.client, False, np.zeros(3), odom_tf=True, rng=rng, frames=frames
    )


@pytest.mark.integration
def test_odometry_on_tf_in_other_frames_is_said_once_per_robot(
    bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    events = Collector()
    listener = RosListener()
    tf_keys = [key(0, f"/robot{i}/tf", TF, False) for i in (1, 2, 3)]
    subs = [bench.client.declare_subscriber("rlutf/robots/*/events", events)]
    subs += [bench.client.declare_subscriber(k, listener) for k in tf_keys]
    robots = [
        _robot(bench, "/robot1", 1, ("odom", "base_link")),  # where base_footprint is expected
        _robot(bench, "/robot2", 2, ("wheel_odom", "base_footprint")),  # where odom is
        _robot(bench, "/robot3", 3, ("odom", "base_footprint")),  # as the settings name them
    ]
    bench.put_map()
    time.sleep(0.3)

    def not_found(robot: str) -> list[dict[str, Any]]:
        said = events.on(f"rlutf/robots/{robot}/events")
        return [e for e in said if e["code"] == "odometry_not_found"]

    def ours(r: RosRobot, k: str) -> list[tuple[str, str]]:  # map -> odom from the service
        return others_transforms(listener, r, k)

    with caplog.at_level(logging.WARNING):
        for r in robots:
            r.initial_pose()
        # tf for more than the 2 s a robot's odometry may be missing (said as tf comes)
        drive(robots, 100, until=lambda: not_found("robot1") and not_found("robot2"))
        assert not_found("robot1") and not_found("robot2")
        drive(robots, 5)
        time.sleep(0.3)
        (e1,) = not_found("robot1")  # once, for 35 tf messages
        assert e1["level"] == "warning" and e1["key"].startswith("0/robot1/tf/")
        for part in ("odom -> base_link", "no odom -> base_footprint", "ros2.base_frame"):
            assert part in e1["message"], e1["message"]
        (e2,) = not_found("robot2")
        assert "wheel_odom -> base_footprint" in e2["message"]
        assert 'ros2.odom_frame = "wheel_odom"' in e2["message"]
        assert not_found("robot3") == []
        # robot3's odometry is found and its map -> odom goes out; robot1's is not
        assert ours(robots[2], tf_keys[2]) and set(ours(robots[2], tf_keys[2])) == {("map", "odom")}
        assert ours(robots[0], tf_keys[0]) == []
        # robot2 sends other frames: said again
        robots[1].frames = ("odom2", "base_footprint")
        drive(robots, 2)
        assert wait_until(lambda: len(not_found("robot2")) == 2)
        assert "odom2 -> base_footprint" in not_found("robot2")[1]["message"]
        # robot1 is set right: its map -> odom goes out, and nothing more is said
        robots[0].frames = ("odom", "base_footprint")
        drive(robots, 5)
        assert wait_until(lambda: len(ours(robots[0], tf_keys[0])) >= 2)
        assert len(not_found("robot1")) == 1
    lines = [r.getMessage() for r in caplog.records if "odometry_not_found" in r.getMessage()]
    assert any("robot1" in line and "base_link" in line for line in lines), lines
    for s in subs:
        s.undeclare()
