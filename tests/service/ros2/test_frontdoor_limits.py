"""What a ROS 2 input costs is bounded as a JSON input's is, over real Zenoh sessions.

Each namespace the front door serves is a robot with liveliness tokens and publishers (about
40 kB and 0.1 s of the router's and the service's time each): only valid input makes one, at
most ``max_robots`` are held, and an evicted robot's go. ROS inputs stamped far ahead of the
service's clock are refused as JSON ones are (``max_stamp_ahead_s``).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from ros_client import TS, RosListener, RosRobot, header, key, quat, scan_msg
from service_harness import WORLD, Bench, Collector, health, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings

pytestmark = pytest.mark.integration

SCAN = "sensor_msgs/msg/LaserScan"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
GRID = "nav_msgs/msg/OccupancyGrid"


@pytest.fixture
def small_bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1"), max_robots=3) as b:
        yield b


def _robot(bench: Bench, ns: str, seed: int, **kw: Any) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 200)
    return RosRobot(ns, WORLD, truth, bench.client, False, np.zeros(3), rng=rng, **kw)


def _tokens(bench: Bench) -> list[str]:
    return [str(r.ok.key_expr) for r in bench.client.liveliness().get("@ros2_lv/**", timeout=2.0)]


def test_malformed_cdr_makes_no_robot_and_robots_stay_within_max_robots(
    small_bench: Bench,
) -> None:
    bench = small_bench
    events = Collector()
    sub = bench.client.declare_subscriber("rlutf/**/events", events)
    bench.put_map()
    time.sleep(0.3)
    # Garbage from 30 namespaces: Events, but no robot, token or publisher for any of them.
    for i in range(30):
        bench.client.put(key(0, f"/junk{i}/scan", SCAN, False), b"\x00\x01\x00\x00garbage")

    # an Event each, on its own key for 20 of them and the others counted in one on rlutf/events
    # (a robot's Events of a code go out for at most 20 robots a second: eventbudget)
    def said() -> int:
        own = sum(bool(events.on(f"rlutf/robots/junk{i}/events")) for i in range(30))
        folded = [
            re.match(r"(\d+) more like it", str(e["message"])) for e in events.on("rlutf/events")
        ]
        return own + sum(int(m.group(1)) for m in folded if m)

    assert wait_until(lambda: said() == 30, timeout=5.0), said()
    assert health(bench.client)["extra"]["ros2_robots"] == {}
    assert not [t for t in _tokens(bench) if "junk" in t]
    # Valid robots: three are held (max_robots), the others refused with robot_limit.
    robots = [_robot(bench, f"/robot{i}", i) for i in range(6)]
    for r in robots[:3]:
        r.initial_pose()
    time.sleep(0.3)
    listener = RosListener()
    pose0 = key(0, "/robot0/amcl_pose", POSE, False)
    subs = [bench.client.declare_subscriber(pose0, listener)]
    for _ in range(5):
        for r in robots:
            r.advance()
        time.sleep(0.05)
    assert wait_until(lambda: any(e["code"] == "robot_limit" for e in events.on("rlutf/events")))
    held = health(bench.client)["extra"]["ros2_robots"]
    assert held == {"robot0": "/robot0", "robot1": "/robot1", "robot2": "/robot2"}
    assert not [t for t in _tokens(bench) if "robot5" in t]
    # the robots held go on
    before = len(listener.on(pose0))
    for _ in range(5):
        robots[0].advance()
        time.sleep(0.05)
    assert wait_until(lambda: len(listener.on(pose0)) >= before + 4)
    for s in [sub, *subs]:
        s.undeclare()


def test_an_evicted_ros_robot_leaves_the_front_door(tmp_path: Path) -> None:
    with running_bench(
        tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1"), robot_idle_s=1.0
    ) as bench:
        bench.put_map()
        time.sleep(0.3)
        r = _robot(bench, "/robot1", 1)
        r.initial_pose()
        for _ in range(3):
            r.advance()
            time.sleep(0.05)
        assert wait_until(lambda: "robot1" in health(bench.client)["extra"]["ros2_robots"])
        assert [t for t in _tokens(bench) if "robot1" in t]
        # silent past robot_idle_s: evicted, and its tokens and publishers undeclared
        assert wait_until(lambda: health(bench.client)["extra"]["ros2_robots"] == {}, timeout=15.0)
        assert wait_until(lambda: not [t for t in _tokens(bench) if "robot1" in t])
        # it comes back with its next input
        r.initial_pose()
        r.advance()
        assert wait_until(lambda: "robot1" in health(bench.client)["extra"]["ros2_robots"])


def test_ros_inputs_stamped_far_ahead_are_refused(tmp_path: Path) -> None:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1")) as bench:
        events, poses = Collector(), Collector()
        subs = [
            bench.client.declare_subscriber("rlutf/robots/*/events", events),
            bench.client.declare_subscriber("rlutf/robots/*/pose", poses),
        ]
        bench.put_map()
        time.sleep(0.3)
        ahead = _robot(bench, "/ahead", 1, t0=time.time_ns() + 365 * 86400 * 10**9)
        ahead.initial_pose()
        for _ in range(5):
            ahead.advance()
            time.sleep(0.05)
        codes = lambda: [e["code"] for e in events.on("rlutf/robots/ahead/events")]  # noqa: E731
        assert wait_until(lambda: "stamp_rejected" in codes())
        time.sleep(0.5)
        assert poses.on("rlutf/robots/ahead/pose") == []
        for s in subs:
            s.undeclare()


def test_scans_in_ever_new_frames_log_a_bounded_number_of_lines(
    small_bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    bench = small_bench
    bench.put_map()
    time.sleep(0.3)
    r = _robot(bench, "/robot1", 1)
    r.initial_pose()
    rng = np.random.default_rng(5)
    with caplog.at_level(logging.WARNING, logger="service.ros2.frontdoor"):
        for i in range(60):
            r.step += 1
            r.odom(r.step)
            msg = scan_msg(WORLD, r.truth[r.step], r.stamp(r.step), rng, f"laser_{i}")
            r.put("scan", SCAN, msg)
            time.sleep(0.01)
        assert wait_until(lambda: health(bench.client)["extra"]["ros2_scans_laser_at_base"] >= 60)
    said = [rec for rec in caplog.records if "tf_static" in rec.getMessage()]
    assert 1 <= len(said) <= 10, len(said)


def _big_grid(stamp_ns: int, cells: int = 600) -> bytes:
    """A square room of ``cells`` x ``cells`` 5 cm cells, walls two cells thick."""
    data = np.zeros((cells, cells), dtype=np.int8)
    data[:2, :] = data[-2:, :] = data[:, :2] = data[:, -2:] = 100
    data[100:140, 100:140] = 100
    t = TS.types
    msg = t["nav_msgs/msg/OccupancyGrid"](
        header=header(stamp_ns, "map"),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
            resolution=0.05,
            width=cells,
            height=cells,
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0), orientation=quat(0.0)
            ),
        ),
        data=data.ravel(),
    )
    return bytes(TS.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))


def test_a_flood_of_grids_on_the_map_topic_is_imported_one_at_a_time(tmp_path: Path) -> None:
    settings = Ros2Settings(enabled=True, map_id="m1", map_topic="map")
    with running_bench(tmp_path, ros2=settings) as bench:
        grid_key = f"0/map/nav_msgs::msg::dds_::OccupancyGrid_/{TS.hash_rihs01(GRID)}"
        stamps = [time.time_ns() + i * 1_000_000_000 for i in range(12)]
        grids = [_big_grid(stamp) for stamp in stamps]
        baseline = threading.active_count()
        peak = [baseline]
        done = threading.Event()

        def watch() -> None:
            while not done.is_set():
                peak[0] = max(peak[0], threading.active_count())
                time.sleep(0.005)

        watcher = threading.Thread(target=watch)
        watcher.start()
        try:
            for raw in grids:
                bench.client.put(grid_key, raw, congestion_control=zenoh.CongestionControl.BLOCK)
            newest = stamps[-1] // 1_000_000  # the version of the last grid: it is imported
            held = lambda: bench.service.maps.get("m1")  # noqa: E731
            assert wait_until(lambda: (m := held()) is not None and m.version == newest, 60.0)
        finally:
            done.set()
            watcher.join()
        # one thread imports, whatever the number of grids (+1: the watcher)
        assert peak[0] - baseline <= 2, peak[0] - baseline


def test_robots_the_service_does_not_hold_leave_the_front_door_when_idle(tmp_path: Path) -> None:
    """A namespace whose inputs the service never takes (another instance owns it, or its
    stamps are refused) is never evicted by this instance: idle, it makes room all the same."""
    with running_bench(
        tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1"), max_robots=2, robot_idle_s=1.0
    ) as bench:
        events = Collector()
        sub = bench.client.declare_subscriber("rlutf/**/events", events)
        bench.put_map()
        time.sleep(0.3)
        ahead = time.time_ns() + 365 * 86400 * 10**9
        for i in range(2):
            r = _robot(bench, f"/ahead{i}", i, t0=ahead)
            r.initial_pose()
            r.advance()
        assert wait_until(lambda: len(health(bench.client)["extra"]["ros2_robots"]) == 2)
        time.sleep(1.5)  # past robot_idle_s
        fresh = _robot(bench, "/fresh", 5)
        fresh.initial_pose()
        for _ in range(3):
            fresh.advance()
            time.sleep(0.05)
        assert wait_until(lambda: "fresh" in health(bench.client)["extra"]["ros2_robots"])
        assert not any(e["code"] == "robot_limit" for e in events.on("rlutf/events"))
        sub.undeclare()


def test_a_frame_id_cannot_forge_a_line_of_the_service_log(
    small_bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    bench = small_bench
    bench.put_map()
    time.sleep(0.3)
    r = _robot(bench, "/robot1", 1)
    r.initial_pose()
    forged = "laser\n2026-12-07 04:00:00,000 ERROR service.live.node: forged\x1b[2J"
    with caplog.at_level(logging.WARNING, logger="service.ros2.frontdoor"):
        r.step += 1
        r.odom(r.step)
        msg = scan_msg(WORLD, r.truth[r.step], r.stamp(r.step), np.random.default_rng(5), forged)
        r.put("scan", SCAN, msg)
        assert wait_until(lambda: health(bench.client)["extra"]["ros2_scans_laser_at_base"] >= 1)
    said = [rec.getMessage() for rec in caplog.records if "tf_static" in rec.getMessage()]
    assert said and all("\n" not in m and "\x1b" not in m for m in said), said


def test_a_full_front_door_makes_room_after_seconds_not_robot_idle_s(tmp_path: Path) -> None:
    """Made-up namespaces, one valid message each, held a full front door for robot_idle_s (an
    hour): every real ROS robot new since was refused."""
    with running_bench(
        tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1"), max_robots=2
    ) as bench:
        assert bench.service.ros2 is not None
        bench.service.ros2.roster.room_idle_ns = 1_000_000_000  # the default, 10 s, is long
        bench.put_map()
        time.sleep(0.3)
        for i in range(2):
            _robot(bench, f"/made_up{i}", i).advance()
        assert wait_until(lambda: len(health(bench.client)["extra"]["ros2_robots"]) == 2)
        time.sleep(1.5)
        fresh = _robot(bench, "/fresh", 5)
        fresh.initial_pose()
        for _ in range(3):
            fresh.advance()
            time.sleep(0.05)
        assert wait_until(lambda: "fresh" in health(bench.client)["extra"]["ros2_robots"])
        assert bench.service.ros2.roster.robots_refused == 0  # the front door refused none
        held = health(bench.client)["extra"]["ros2_robots"]
        assert "made_up0" not in held or "made_up1" not in held, held
