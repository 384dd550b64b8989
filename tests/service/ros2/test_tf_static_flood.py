"""tf_static from made-up namespaces cannot take the laser's pose from a real robot.

Found by a reviewer attacking ``rlutf serve --ros2`` as a hostile client: the front door keeps
a tf_static tree per namespace, at most ``max_robots`` of them, and a namespace that only ever
put tf_static (never a scan: no robot) kept its tree for good. A burst of tf_static on that
many made-up namespaces filled them; every ROS robot that came later had its tf_static
dropped, so its laser was taken at the base: 25 cm off on every scan, and its poses with it.
Now, when the trees are full, the oldest tree of a namespace that is no robot gives way. And a
tf_static over ``max_payload_bytes`` is refused before it is decoded, as other ROS inputs are.
Real Zenoh sessions on loopback.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, RosListener, RosRobot, T, key, tf_msg
from service_harness import WORLD, Bench, Collector, running_bench, wait_until

from rlutf.sim import make_trajectory
from service.config import Ros2Settings

pytestmark = pytest.mark.integration

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1"), max_robots=4) as b:
        yield b


def _robot(bench: Bench, ns: str, seed: int, laser: np.ndarray) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 200)
    origin = np.array([0.5, -0.7, 0.4])
    return RosRobot(ns, WORLD, truth, bench.client, False, origin, rng=rng, laser=laser)


def test_tf_static_of_made_up_namespaces_leaves_room_for_a_real_robots(bench: Bench) -> None:
    bench.put_map()
    time.sleep(0.3)
    laser = np.array([0.25, 0.05, 0.1])  # 25 cm ahead: ignoring it misses by that much
    for i in range(12):  # three times max_robots, none of them ever a robot
        _robot(bench, f"/fake{i}", 100 + i, laser).tf_static()
    time.sleep(0.5)
    r = _robot(bench, "/robot1", 8, laser)
    listener = RosListener()
    pose_key = key(0, "/robot1/amcl_pose", POSE, False)
    sub = bench.client.declare_subscriber(pose_key, listener)
    r.tf_static()
    time.sleep(0.3)
    r.initial_pose()
    time.sleep(0.3)
    for _ in range(20):
        r.advance()
        time.sleep(0.1)
    assert wait_until(lambda: len(listener.on(pose_key)) >= 15)
    errors = []
    for raw, _ in listener.on(pose_key)[-5:]:
        m = TS.deserialize_cdr(raw, POSE)
        i = round((m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec - r.t0) / 1e8)
        p = m.pose.pose.position
        errors.append(math.hypot(p.x - r.truth[i, 0], p.y - r.truth[i, 1]))
    health = json.loads(bench.service.health())
    assert health["extra"]["ros2_scans_laser_at_base"] == 0
    assert max(errors) < 0.05, errors
    sub.undeclare()


def test_a_tf_static_over_the_payload_limit_is_refused_undecoded(bench: Bench) -> None:
    """Every other ROS input over ``max_payload_bytes`` was refused before decoding; tf_static
    was decoded whatever its size (10 MB, 100,000 transforms: 1.7 s of the service's CPU, in
    a Zenoh callback)."""
    events = Collector()
    sub = bench.client.declare_subscriber("rlutf/events", events)
    r = _robot(bench, "/big", 3, np.array([0.25, 0.05, 0.1]))
    one = tf_msg(np.zeros(3), r.stamp(0), "base_footprint", "base_link")
    msg = T["tf2_msgs/msg/TFMessage"](transforms=list(one.transforms) * 12_000)  # 1.2 MB
    r.put("tf_static", "tf2_msgs/msg/TFMessage", msg)
    assert events.wait_for(
        lambda: any("payload too large" in e["message"] for e in events.on("rlutf/events"))
    )
    said = [e for e in events.on("rlutf/events") if "payload too large" in e["message"]]
    assert said[0]["code"] == "invalid_key" and "tf_static" in said[0]["key"]
    sub.undeclare()
