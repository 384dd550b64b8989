"""A robot whose scans come but no Odometry on its odometry topic (``ros2.odom_source =
"odom"``, the default) is said: with the advice to read it from tf when its tf carries it. Alone,
with the tf watch on real Zenoh sessions, and on a running service."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from ros_client import TS, RosListener, RosRobot, drive, key, others_transforms, tf_msg
from service_harness import WORLD, Bench, Collector, health, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings
from service.live.sessions import client_config, free_port, session_config
from service.ros2.frames import Pair, odometry_like
from service.ros2.odomwatch import MissingOdometry
from service.ros2.tfwatch import TfWatch

S = 1_000_000_000
TF = "tf2_msgs/msg/TFMessage"


def _missing(**kw: Any) -> MissingOdometry:
    settings = Ros2Settings(enabled=True, map_id="m1", **kw)
    return MissingOdometry(settings, time.time_ns, 1_000_000, 2 * S, S // 2)


# ----------------------------------------------------------------------------------- alone
def test_scans_without_odometry_are_said_after_the_wait_and_once() -> None:
    m = _missing()
    assert m.scan("r1", "/r1", 0) is None  # its odometry may only be late
    assert m.scan("r1", "/r1", 1 * S) is None
    assert m.tf.watched() == 1  # its tf is looked at from half a second in
    said = m.scan("r1", "/r1", 2 * S)
    assert said is not None
    for part in (
        "ROS robot r1: no odometry",
        "for 2.0 s",
        "no nav_msgs/Odometry on /r1/odom",  # the topic waited on
        'ros2.odom_topic = "odom"',
        "no map -> odom is published",
        "Its tf (/r1/tf) showed no odom -> base_footprint either",
        "publish its nav_msgs/Odometry on /r1/odom, or set ros2.odom_topic",
    ):
        assert part in said, said
    assert "--ros-odom tf" not in said
    assert m.said() == 1
    for t in range(3, 8):
        assert m.scan("r1", "/r1", t * S) is None  # said once
    # odometry comes: forgotten, its tf watched no more; said again if it goes missing again
    m.odometry("r1")
    assert m.said() == 0
    assert m.scan("r1", "/r1", 8 * S) is None
    assert m.scan("r1", "/r1", 9 * S) is None
    assert m.scan("r1", "/r1", 10 * S) is not None


def test_tf_carrying_the_odometry_is_advised_and_a_change_said_again() -> None:
    m = _missing()
    m.scan("r1", "/r1", 0)
    m.scan("r1", "/r1", S)  # its tf watched from here
    m.on_tf("r1", [("map", "odom"), ("base_link", "laser")])  # nothing like its odometry
    first = m.scan("r1", "/r1", 2 * S)
    assert first is not None and "--ros-odom tf" not in first
    m.on_tf("r1", [("odom", "base_link")])  # its odometry, of another base frame
    assert m.scan("r1", "/r1", 3 * S) is None  # not at once: the service would hold it back
    again = m.scan("r1", "/r1", 4 * S)
    assert again is not None
    assert "Its tf (/r1/tf) carries odom -> base_link" in again
    assert '--ros-odom tf (ros2.odom_source = "tf") with ros2.base_frame = "base_link"' in again
    m.on_tf("r1", [("odom", "base_footprint")])  # its odometry itself: the watch ends
    assert wait_until(lambda: m.tf.watched() == 0, 1.0)
    third = m.scan("r1", "/r1", 6 * S)
    assert third is not None and "carries odom -> base_footprint: to fix" in third
    assert third.endswith('--ros-odom tf (ros2.odom_source = "tf")')
    assert m.scan("r1", "/r1", 9 * S) is None  # nothing new


def test_late_odometry_is_not_said() -> None:
    m = _missing()
    for i in range(100):  # scans at 10 Hz, odometry at 1 Hz
        assert m.scan("r1", "/r1", i * S // 10) is None
        if i % 10 == 9:
            m.odometry("r1")
    assert m.tf.watched() == 0  # never missing long enough to look at its tf


def test_what_is_remembered_and_watched_is_bounded() -> None:
    m = _missing()
    m.kept = 3
    for i in range(40):
        m.scan(f"r{i}", f"/r{i}", 0)
        m.scan(f"r{i}", f"/r{i}", S)
        assert len(m._waiting) <= 3
    assert m.tf.watched() == m.tf.most  # 16: the others are not watched
    forged = "x\nERROR forged line" + "y" * 10_000
    m.scan("forger", "/forger", 0)
    m.scan("forger", "/forger", S)
    m.on_tf("forger", [("odom", forged)])
    said = m.scan("forger", "/forger", 2 * S)
    assert said is not None and "\n" not in said and "\\x0a" in said and len(said) < 3000


def test_the_transform_most_like_odometry() -> None:
    def like(pairs: list[Pair]) -> Pair | None:
        return odometry_like(pairs, "map", "odom", "base_footprint")

    assert like([("map", "odom"), ("base_link", "laser")]) is None
    assert like([("wheel_odom", "base_footprint")]) == ("wheel_odom", "base_footprint")
    assert like([("odom", "base_link"), ("odom", "base_footprint")]) == ("odom", "base_footprint")
    assert like([("odom", "b" * 1000)]) == ("odom", "b" * 200)


def test_the_tf_watch_subscribes_for_a_while_over_real_sessions() -> None:
    port = free_port()
    router = zenoh.open(session_config("router", listen=[f"tcp/127.0.0.1:{port}"]))
    robot = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    seen: list[tuple[str, list[Pair]]] = []
    watch = TfWatch(0, "tf", lambda r, f: seen.append((r, f)), time.time_ns, 10_000, most=1,
                    lifetime_ns=3 * S)  # fmt: skip
    watch.start(router)
    try:
        k1, k2 = key(0, "/r1/tf", TF, False), key(0, "/r2/tf", TF, True)
        raw = bytes(TS.serialize_cdr(tf_msg(np.zeros(3), 1, "odom", "base_footprint"), TF))

        def put(k: str, payload: bytes = raw) -> None:
            robot.put(k, payload)
            time.sleep(0.05)

        put(k1)
        assert seen == []  # not watched
        assert watch.want("/r1", "r1") and not watch.want("/r2", "r2")  # one at most
        assert wait_until(lambda: (put(k1), seen)[1], 2.0)
        assert seen[0] == ("r1", [("odom", "base_footprint")])
        n = len(seen)
        put(k2)  # not watched
        put(k1[: -len("RIHS01_") - 64] + "TypeHashNotSupported", b"\x00\x01\x00\x00 not a tf")
        put(k1, b"x" * 20_000)  # larger than the payloads read
        put(k1)
        assert wait_until(lambda: len(seen) == n + 1, 2.0)
        time.sleep(0.2)
        assert len(seen) == n + 1  # the malformed and the large: left alone
        # after its lifetime, it is watched no more and makes room
        assert wait_until(lambda: watch.watched() == 0, 5.0)
        n = len(seen)
        put(k1)
        put(k1)
        assert len(seen) == n
        assert watch.want("/r2", "r2")
        watch.drop("/r2")
        assert wait_until(lambda: watch.watched() == 0, 2.0)
    finally:
        watch.close()
        robot.close()
        router.close()


# ---------------------------------------------------------------------------- on a service
@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1")) as b:
        yield b


def _robot(bench: Bench, ns: str, seed: int, odom_tf: bool) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 300)
    origin = np.array([1.0, -0.5, 0.3])
    return RosRobot(ns, WORLD, truth, bench.client, False, origin, odom_tf=odom_tf, rng=rng)


@pytest.mark.integration
def test_odometry_on_tf_only_is_said_with_the_advice_and_odom_then_localizes(
    bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    events = Collector()
    listener = RosListener()
    tf1 = key(0, "/robot1/tf", TF, False)
    pose1 = key(0, "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", False)
    subs = [bench.client.declare_subscriber("rlutf/robots/*/events", events)]
    subs += [bench.client.declare_subscriber(k, listener) for k in (tf1, pose1)]
    robots = [
        _robot(bench, "/robot1", 1, odom_tf=True),  # odometry on tf only: odom -> base_footprint
        _robot(bench, "/robot2", 2, odom_tf=False),  # as the settings expect
    ]
    bench.put_map()
    time.sleep(0.3)

    def not_found(robot: str) -> list[dict[str, Any]]:
        said = events.on(f"rlutf/robots/{robot}/events")
        return [e for e in said if e["code"] == "odometry_not_found"]

    def ours() -> list[tuple[str, str]]:  # map -> odom the service published on robot1's tf
        return others_transforms(listener, robots[0], tf1)

    with caplog.at_level(logging.WARNING):
        for r in robots:
            r.initial_pose()
        # scans for more than the 2 s a robot's odometry may be missing
        drive(robots, 120, until=lambda: not_found("robot1"))
        (said,) = not_found("robot1")
        assert said["level"] == "warning" and said["key"].startswith("0/robot1/scan/")
        for part in (
            "no nav_msgs/Odometry on /robot1/odom",
            "Its tf (/robot1/tf) carries odom -> base_footprint",
            '--ros-odom tf (ros2.odom_source = "tf")',
        ):
            assert part in said["message"], said["message"]
        assert not_found("robot2") == []
        assert wait_until(
            lambda: health(bench.client)["extra"]["ros2_robots_without_odometry"] == 1
        )
        # what such a robot gets: poses (localized with no motion), but no map -> odom
        assert listener.on(pose1) and ours() == []
        assert wait_until(lambda: bench.service.ros2.odometry_watch.tf.watched() == 0)  # seen
        # its Odometry on odom now: map -> odom published, and nothing more said
        robots[0].odom_tf = False
        drive(robots, 60)
        assert wait_until(lambda: len(ours()) >= 10)
        assert set(ours()) == {("map", "odom")}
        assert len(not_found("robot1")) == 1 and not_found("robot2") == []
        assert health(bench.client)["extra"]["ros2_robots_without_odometry"] == 0
    lines = [r.getMessage() for r in caplog.records if "odometry_not_found" in r.getMessage()]
    assert any("robot1" in line and "--ros-odom tf" in line for line in lines), lines
    for s in subs:
        s.undeclare()
