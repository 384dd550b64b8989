"""What a ROS 2 operator relies on: a warning without a map, AMCL's global localization service,
and an ``amcl_pose`` a ROS subscriber can recover, over real Zenoh sessions.

The service call comes from zenoh-ros2-sdk (a third-party rmw_zenoh client: its own keys, CDR
and attachment, and its own computation of the service's type hash); the robot's messages from
rosbags' CDR (``ros_client``).
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
import zenoh.ext
from ros_client import TS, RosListener, RosRobot, key
from service_harness import WORLD, Bench, Collector, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings
from service.live.sessions import free_port
from service.ros2.entities import no_map_warning

pytestmark = pytest.mark.integration

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"


@pytest.fixture
def ros_bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1")) as b:
        yield b


def _robot(bench: Bench, ns: str, seed: int) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 200)
    origin = np.array([0.5, -0.7, 0.4])
    return RosRobot(ns, WORLD, truth, bench.client, False, origin, rng=rng)


def _track(bench: Bench, r: RosRobot, steps: int) -> None:
    bench.put_map()
    time.sleep(0.3)
    r.initial_pose()
    time.sleep(0.5)
    for _ in range(steps):
        r.advance()
        time.sleep(0.03)


@pytest.mark.parametrize(
    "layout", [("--workers", "0"), ("--processes", "2")], ids=["one process", "a host"]
)
def test_serve_ros2_without_a_map_warns_at_start(tmp_path: Path, layout: tuple[str, ...]) -> None:
    """Once, whatever the layout (a host of N processes said it N times)."""
    port = free_port()
    exe = Path(sys.executable).with_name("rlutf")
    cmd = [str(exe), "serve", "--ros2", "--listen", f"tcp/127.0.0.1:{port}"]
    cmd += ["--store", str(tmp_path / "store"), "--no-record", "--no-state", *layout]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("RLUTF_", "ROS_"))}
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env
    )
    lines: list[str] = []
    try:
        assert proc.stderr is not None
        end = time.monotonic() + 180
        while time.monotonic() < end:
            line = proc.stderr.readline()
            if not line:
                break
            lines.append(line)
            if "rlutf serve: ready" in line:  # started: no ROS message came in
                break
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    text = "".join(lines)
    assert "rlutf serve: ready" in text, text
    assert sum("no map given" in line for line in lines) == 1, text
    warning = next((line for line in lines if "no map given" in line), text)
    assert "WARNING" in warning and "--ros-map MAP_ID" in warning
    assert "initialpose" in warning and "reinitialize_global_localization" in warning
    # with a map (or a map per robot), nothing to say
    assert no_map_warning(Ros2Settings(enabled=True, map_id="m1")) is None
    per_robot = no_map_warning(Ros2Settings(enabled=True, robots={"robot1": {"map_id": "m1"}}))
    assert per_robot is not None and "without ros2.robots.NS.map_id" in per_robot


def test_reinitialize_global_localization_from_a_ros_client(ros_bench: Bench) -> None:
    from zenoh_ros2_sdk import ROS2ServiceClient
    from zenoh_ros2_sdk.session import ZenohSession

    bench = ros_bench
    events = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/robot1/events", events)
    json_poses = Collector()
    sub2 = bench.client.declare_subscriber("rlutf/robots/robot1/pose", json_poses)
    r1 = _robot(bench, "/robot1", 1)
    _track(bench, r1, 10)
    assert wait_until(lambda: len(json_poses.on("rlutf/robots/robot1/pose")) >= 5)
    # the service is in the ROS graph: `ros2 service list` would show it
    tokens = [str(r.ok.key_expr) for r in bench.client.liveliness().get("@ros2_lv/0/**") if r.ok]
    assert any(
        "/SS/" in t
        and "%robot1%reinitialize_global_localization/std_srvs::srv::dds_::Empty_/RIHS01_" in t
        for t in tokens
    )

    ZenohSession._instance = None  # the SDK keeps one session a process: this router's
    port = int(bench.endpoint.rsplit(":", 1)[1])
    empty = "uint8 structure_needs_at_least_one_member"  # what rosidl makes of an empty message
    client = ROS2ServiceClient(
        "/robot1/reinitialize_global_localization",
        "std_srvs/srv/Empty",
        request_definition=empty,
        response_definition=empty,
        router_port=port,
        timeout=5.0,
    )
    try:
        response = client.call()
    finally:
        client.close()
    assert response is not None  # an Empty_Response, matched to the call by its attachment
    assert bench.service.ros2 is not None and bench.service.ros2.globalloc.calls == 1
    for _ in range(30):
        r1.advance()
        time.sleep(0.03)
    codes = lambda: [e["code"] for e in events.on("rlutf/robots/robot1/events")]  # noqa: E731
    assert wait_until(lambda: "relocalizing" in codes()), codes()
    assert wait_until(lambda: "relocalized" in codes(), 20.0), codes()
    sub.undeclare()
    sub2.undeclare()


def test_a_call_for_a_robot_without_a_map_is_refused(tmp_path: Path) -> None:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True)) as bench:
        events = Collector()
        sub = bench.client.declare_subscriber("rlutf/robots/robot7/events", events)
        # a Humble client's key (no type hash)
        k = "0/robot7/reinitialize_global_localization/std_srvs::srv::dds_::Empty_/"
        k += "TypeHashNotSupported"
        att = struct.pack("<qqB", 1, time.time_ns(), 16) + b"\x05" * 16
        replies = list(
            bench.client.get(
                k,
                payload=b"\x00\x01\x00\x00\x00",
                attachment=att,
                target=zenoh.QueryTarget.ALL_COMPLETE,
                timeout=5.0,
            )
        )
        assert len(replies) == 1 and replies[0].err is not None
        assert "--ros-map" in replies[0].err.payload.to_string()
        assert wait_until(lambda: events.on("rlutf/robots/robot7/events"))
        ev = events.on("rlutf/robots/robot7/events")[0]
        assert ev["code"] == "invalid_message" and "no map" in ev["message"]
        sub.undeclare()


def _ros_subscription(session: zenoh.Session, key_expr: str, callback: Any) -> Any:
    """A subscription as rmw_zenoh declares one for a reliable transient-local topic
    (``rmw_subscription_data.cpp``: history of late publishers, heartbeat recovery)."""
    return zenoh.ext.declare_advanced_subscriber(
        session,
        key_expr,
        callback,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        recovery=zenoh.ext.RecoveryConfig(heartbeat=True),
        subscriber_detection=True,
    )


def test_amcl_pose_has_rmw_zenohs_heartbeat_and_a_ros_subscriber_recovers(
    ros_bench: Bench,
) -> None:
    bench = ros_bench
    r1 = _robot(bench, "/robot1", 1)
    pose_key = key(0, "/robot1/amcl_pose", POSE, False)
    heartbeats: list[tuple[str, int]] = []

    def on_heartbeat(s: zenoh.Sample) -> None:
        heartbeats.append((str(s.key_expr), struct.unpack("<I", s.payload.to_bytes())[0]))

    hb_sub = bench.client.declare_subscriber(f"{pose_key}/@adv/**", on_heartbeat)
    got = RosListener()
    misses: list[Any] = []
    ros_sub = _ros_subscription(bench.client, pose_key, got)
    miss_listener = ros_sub.sample_miss_listener(misses.append)
    _track(bench, r1, 20)
    assert wait_until(lambda: len(got.on(pose_key)) >= 10)
    time.sleep(1.2)  # a heartbeat period after the last pose
    # the heartbeat carries the publisher's last sequence number, sent while it changes
    assert heartbeats, "no sample-miss heartbeat on the amcl_pose publisher"
    assert all("/@adv/pub/" in k for k, _ in heartbeats)
    seqs = [s for _, s in heartbeats]
    assert seqs == sorted(seqs) and seqs[-1] >= len(got.on(pose_key)) - 1
    assert not misses
    last = TS.deserialize_cdr(got.on(pose_key)[-1][0], POSE)
    # a subscriber that comes late recovers the last pose from the publisher's cache
    late = RosListener()
    late_sub = _ros_subscription(bench.client, pose_key, late)
    assert wait_until(lambda: late.on(pose_key), 5.0)
    recovered = TS.deserialize_cdr(late.on(pose_key)[-1][0], POSE)
    assert recovered.header.stamp == last.header.stamp
    miss_listener.undeclare()
    for s in (hb_sub, ros_sub, late_sub):
        s.undeclare()
