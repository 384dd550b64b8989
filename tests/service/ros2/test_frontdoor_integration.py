"""ROS 2 robots on the service over real Zenoh sessions: rmw_zenoh keys, CDR, attachments."""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from ros_client import (
    TS,
    RosListener,
    RosRobot,
    header,
    initialpose_msg,
    key,
    pose_of_tf,
    quat,
    scan_msg,
    yaw,
)
from service_harness import WORLD, Bench, Collector, running_bench, wait_until

from rlutf.motion import compose
from rlutf.sim import make_trajectory
from service.config import Ros2Settings, Settings
from service.live.node import LocalizationService
from service.live.sessions import client_config, free_port
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile
from service.logs.replay import replay

pytestmark = pytest.mark.integration

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"


def _bench(tmp_path: Path, **ros2: object) -> Iterator[Bench]:
    with running_bench(tmp_path, ros2=Ros2Settings(enabled=True, map_id="m1", **ros2)) as b:
        yield b


@pytest.fixture
def ros_bench(tmp_path: Path) -> Iterator[Bench]:
    yield from _bench(tmp_path)


@pytest.fixture
def ros_bench_tf(tmp_path: Path) -> Iterator[Bench]:
    yield from _bench(tmp_path, odom_source="tf")


def _robot(bench: Bench, ns: str, seed: int, humble: bool, **kw: object) -> RosRobot:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, 200)
    origin = np.array([1.5 * seed, -0.7, 0.4 * seed])  # odom's origin differs from the map's
    return RosRobot(ns, WORLD, truth, bench.client, humble, origin, rng=rng, **kw)  # type: ignore[arg-type]


def _check_attachments(samples: list[tuple[bytes, bytes | None]]) -> None:
    seqs, gids = [], set()
    for _, att in samples:
        assert att is not None and len(att) == 33
        seq, ts, n = struct.unpack_from("<qqB", att)
        assert n == 16
        assert abs(ts - time.time_ns()) < 60e9
        seqs.append(seq)
        gids.add(att[17:])
    assert seqs == list(range(1, len(seqs) + 1))
    assert len(gids) == 1


def _start(bench: Bench, robots: list[RosRobot]) -> None:
    """The map into the store, then each robot's initial pose (RViz's 2D Pose Estimate)."""
    bench.put_map()
    time.sleep(0.3)
    for r in robots:
        r.initial_pose()
    time.sleep(0.5)


def _drive(robots: list[RosRobot], steps: int, pause: float = 0.03) -> None:
    for _ in range(steps):
        for r in robots:
            r.advance()
        time.sleep(pause)


def _last_pose_error(listener: RosListener, r: RosRobot, pose_key: str) -> tuple[int, float]:
    raw, _ = listener.on(pose_key)[-1]
    m = TS.deserialize_cdr(raw, POSE)
    assert m.header.frame_id == "map"
    stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
    i = round((stamp - r.t0) / 1e8)
    p = m.pose.pose
    cov = m.pose.covariance.reshape(6, 6)
    assert cov[0, 0] > 0 and cov[1, 1] > 0 and cov[5, 5] > 0  # the estimate's, not zeros
    assert cov[2, 2] == 0 and cov[3, 3] == 0 and cov[4, 4] == 0
    err = math.hypot(p.position.x - r.truth[i, 0], p.position.y - r.truth[i, 1])
    assert abs(math.remainder(yaw(p.orientation) - r.truth[i, 2], math.tau)) < 0.05
    return i, err


def test_two_namespaced_robots_humble_and_jazzy_keys(ros_bench: Bench) -> None:
    bench = ros_bench
    listener = RosListener()
    r1 = _robot(bench, "/robot1", 1, humble=False)
    r2 = _robot(bench, "/robot2", 2, humble=True)
    outs = {
        r: (
            key(0, f"{r.namespace}/amcl_pose", POSE, r.humble),
            key(0, f"{r.namespace}/tf", TF, r.humble),
        )
        for r in (r1, r2)
    }
    # Exact keys: a Humble robot listens on TypeHashNotSupported, a Jazzy one on RIHS01.
    subs = [bench.client.declare_subscriber(k, listener) for pair in outs.values() for k in pair]
    diagnostics = key(0, "/robot1/diagnostics", DIAGNOSTICS, False)
    subs.append(bench.client.declare_subscriber(diagnostics, listener))
    events = Collector()
    subs.append(bench.client.declare_subscriber("rlutf/robots/*/events", events))
    json_poses = Collector()
    subs.append(bench.client.declare_subscriber("rlutf/robots/*/pose", json_poses))
    _start(bench, [r1, r2])
    _drive([r1, r2], 25)
    for r, (pose_key, tf_key) in outs.items():
        assert wait_until(lambda pk=pose_key: len(listener.on(pk)) >= 15), pose_key
        _, err = _last_pose_error(listener, r, pose_key)
        assert err < 0.05, (r.namespace, err)
        _check_attachments(listener.on(pose_key))
        _check_attachments(listener.on(tf_key))
        stamp, parent, child, map_odom = pose_of_tf(listener.on(tf_key)[-1][0])
        assert (parent, child) == ("map", "odom")
        j = round((stamp - 1_000_000_000 - r.t0) / 1e8)  # stamped ahead by the tolerance
        assert abs(j - r.step) <= 3
        assert np.hypot(*(map_odom[:2] - r.odom_origin[:2])) < 0.05
        base = compose(map_odom, r.odom_pose(j))
        assert np.hypot(*(base[:2] - r.truth[j, :2])) < 0.05
    # The pose's quality, as a DiagnosticArray on the robot's diagnostics.
    _check_attachments(listener.on(diagnostics))
    quality = TS.deserialize_cdr(listener.on(diagnostics)[-1][0], DIAGNOSTICS).status[0]
    values = {kv.key: kv.value for kv in quality.values}
    assert (quality.level, quality.hardware_id, values["position_initialized"]) == (
        0,
        "robot1",
        "true",
    )
    assert float(values["localization_score"]) > 0.8
    assert 0.0 < float(values["deviation_range"]) < 0.05
    # The JSON front door's outputs are there for ROS robots too.
    last = json_poses.on("rlutf/robots/robot1/pose")[-1]
    assert last["robot_id"] == "robot1"
    assert 0.0 <= last["localization_score"] <= 1.0 and last["deviation_range"] > 0.0
    assert json_poses.on("rlutf/robots/robot2/pose")
    # Graph: ros2 node list / topic list would show the service and its topics.
    tokens = [str(r.ok.key_expr) for r in bench.client.liveliness().get("@ros2_lv/0/**") if r.ok]
    assert any("/NN/%/%/rlutf_localization" in t for t in tokens)
    mp = [t for t in tokens if "/MP/" in t]
    assert any(
        "%robot1%amcl_pose/" in t and "RIHS01_" in t and t.endswith(":1:,1:,:,:,,") for t in mp
    )
    assert any("%robot2%amcl_pose/" in t and "/TypeHashNotSupported/" in t for t in mp)
    assert any(
        "/MS/" in t and "%robot1%scan/sensor_msgs::msg::dds_::LaserScan_/" in t for t in tokens
    )
    assert not events.on("rlutf/robots/robot1/events")
    for s in subs:
        s.undeclare()


def test_bad_ros_input_gets_an_event_and_loses_nothing_else(ros_bench: Bench) -> None:
    bench = ros_bench
    listener = RosListener()
    r1 = _robot(bench, "/robot1", 3, humble=False)
    r2 = _robot(bench, "/robot2", 4, humble=False)
    pose1 = key(0, "/robot1/amcl_pose", POSE, False)
    pose2 = key(0, "/robot2/amcl_pose", POSE, False)
    subs = [bench.client.declare_subscriber(k, listener) for k in (pose1, pose2)]
    events = Collector()
    subs.append(bench.client.declare_subscriber("rlutf/**/events", events))
    _start(bench, [r1, r2])
    _drive([r1, r2], 8)
    # malformed CDR on a valid key
    r1.put_raw("scan", "sensor_msgs/msg/LaserScan", b"\x00\x01\x00\x00garbage")
    # a wrong type on the scan topic
    s = TS.types["std_msgs/msg/String"](data="hello")
    r1.put("scan", "std_msgs/msg/String", s)
    # a scan whose ranges are all NaN (no return at all), and one with a NaN angle
    m = scan_msg(WORLD, r1.truth[r1.step], r1.stamp(r1.step) + 1, np.random.default_rng(9))
    m.ranges[:] = np.nan
    r1.put("scan", "sensor_msgs/msg/LaserScan", m)
    m.angle_increment = float("nan")
    m.ranges[:] = 2.0
    r1.put("scan", "sensor_msgs/msg/LaserScan", m)
    # an initial pose in another frame, and a namespace that is no robot id
    r2.put("initialpose", POSE, initialpose_msg(r2.truth[0] + 3.0, r2.stamp(r2.step), "odom"))
    bench.client.put(key(0, "/a.b/scan", "sensor_msgs/msg/LaserScan", False), b"\x00\x01\x00\x00")
    time.sleep(0.3)
    _drive([r1, r2], 15)
    assert wait_until(lambda: len(listener.on(pose1)) >= 18 and len(listener.on(pose2)) >= 18)
    ev1 = [e["message"] for e in events.on("rlutf/robots/robot1/events")]
    codes1 = [e["code"] for e in events.on("rlutf/robots/robot1/events")]
    assert any("malformed CDR" in m for m in ev1), ev1
    assert any("carries std_msgs/msg/String" in m for m in ev1), ev1
    assert any("angle_increment" in m for m in ev1), ev1
    assert "lost" in codes1  # the all-NaN scan: too few returns
    ev2 = [e["message"] for e in events.on("rlutf/robots/robot2/events")]
    assert any("frame_id" in m and "'odom'" in m for m in ev2), ev2
    assert any(e["code"] == "invalid_key" for e in events.on("rlutf/events"))
    # Both robots still track their truth: nothing else was lost.
    for r, k in ((r1, pose1), (r2, pose2)):
        _, err = _last_pose_error(listener, r, k)
        assert err < 0.05
    health = json.loads(
        next(iter(bench.client.get("rlutf/service/*/health", timeout=2.0))).ok.payload.to_bytes()
    )
    assert health["rejected"] >= 5
    assert health["extra"]["ros2_robots"] == {"robot1": "/robot1", "robot2": "/robot2"}
    for sub in subs:
        sub.undeclare()


def test_odometry_from_tf_and_no_namespace(ros_bench_tf: Bench) -> None:
    bench = ros_bench_tf
    listener = RosListener()
    r = _robot(bench, "", 5, humble=False, odom_tf=True)
    pose_key = key(0, "/amcl_pose", POSE, False)
    tf_key = key(0, "/tf", TF, False)
    subs = [bench.client.declare_subscriber(k, listener) for k in (pose_key, tf_key)]
    _start(bench, [r])
    _drive([r], 20)
    assert wait_until(lambda: len(listener.on(pose_key)) >= 15)
    _, err = _last_pose_error(listener, r, pose_key)
    assert err < 0.05
    # the tf subscriber also hears the robot's own odom -> base; ours is map -> odom
    ours = [pose_of_tf(raw) for raw, att in listener.on(tf_key) if att and att[17:] != r.gid]
    assert ours and all((p, c) == ("map", "odom") for _, p, c, _ in ours)
    assert np.hypot(*(ours[-1][3][:2] - r.odom_origin[:2])) < 0.05
    assert "robot" in bench.service.ros2.robots()  # type: ignore[union-attr]
    for s in subs:
        s.undeclare()


def test_a_live_ros_run_is_recorded_as_json_and_replays_exactly(tmp_path: Path) -> None:
    port = free_port()
    settings = Settings(
        listen=[f"tcp/127.0.0.1:{port}"],
        store_dir=tmp_path / "store",
        record_dir=tmp_path / "logs",
        workers=1,  # a worker process: inputs cross to it as their JSON payloads
        instance="ros-live",
        event_interval_s=0.0,
        ros2=Ros2Settings(enabled=True, map_id="m1"),
    )
    service = LocalizationService(
        settings, recorder=McapRecorder(settings.record_dir, instance=settings.instance)
    ).start()
    client = zenoh.open(client_config(f"tcp/127.0.0.1:{port}"))
    bench = Bench(service, client, "", WORLD, tmp_path / "store")
    try:
        listener = RosListener()
        r1 = _robot(bench, "/robot1", 6, humble=True)
        pose_key = key(0, "/robot1/amcl_pose", POSE, True)
        sub = client.declare_subscriber(pose_key, listener)
        _start(bench, [r1])
        _drive([r1], 15, pause=0.1)
        last = r1.stamp(r1.step)

        def answered() -> bool:
            got = [TS.deserialize_cdr(raw, POSE).header.stamp for raw, _ in listener.on(pose_key)]
            return any(t.sec * 1_000_000_000 + t.nanosec == last for t in got)

        assert wait_until(answered), service.health()  # a worker starting may drop early scans
        sub.undeclare()
    finally:
        client.close()
        service.close()
    (log,) = sorted((tmp_path / "logs").glob("*.mcap"))
    with LogFile(log) as lf:
        channels = {(c.topic, c.schema_name) for c in lf.channels()}
    assert ("rlutf/robots/robot1/scan", "rlutf.LaserScan") in channels
    assert ("rlutf/robots/robot1/initialpose", "rlutf.InitialPose") in channels
    result = replay([log], tmp_path / "replayed.mcap")
    recorded = [p.payload for p in result.recorded["robot1"]]
    assert len(recorded) >= 5  # scans the busy worker dropped are dropped again by replay
    assert recorded == [p.payload for p in result.recomputed["robot1"]][: len(recorded)]


@pytest.fixture
def ros_bench_map(tmp_path: Path) -> Iterator[Bench]:
    yield from _bench(tmp_path, map_topic="map")


def _grid_msg(stamp_ns: int) -> bytes:
    """A 5 m x 4 m room, walls two cells thick, a 1 m box inside, origin at (-1, -2)."""
    res = 0.05
    data = np.zeros((80, 100), dtype=np.int8)
    data[:2, :] = data[-2:, :] = data[:, :2] = data[:, -2:] = 100
    data[30:50, 40:60] = 100
    data[0, 0] = -1
    t = TS.types
    msg = t["nav_msgs/msg/OccupancyGrid"](
        header=header(stamp_ns, "map"),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
            resolution=res,
            width=100,
            height=80,
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=-1.0, y=-2.0, z=0.0),
                orientation=quat(0.0),
            ),
        ),
        data=data.ravel(),
    )
    return bytes(TS.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))


def test_maps_from_an_occupancy_grid_topic(ros_bench_map: Bench) -> None:
    bench = ros_bench_map
    events = Collector()
    sub = bench.client.declare_subscriber("rlutf/events", events)
    grid_key = (
        f"0/map/nav_msgs::msg::dds_::OccupancyGrid_/{TS.hash_rihs01('nav_msgs/msg/OccupancyGrid')}"
    )
    bench.client.put(grid_key, b"\x00\x01\x00\x00broken")
    bench.client.put(grid_key, _grid_msg(time.time_ns()))
    assert wait_until(lambda: "m1" in bench.service.maps_held(), 20.0)
    stored = json.loads((bench.store / "m1.json").read_text())
    ring = np.array(stored["geometry"]["coordinates"][0])
    assert np.allclose(ring.min(axis=0), [-0.9, -1.9], atol=0.06)  # inside the walls
    assert np.allclose(ring.max(axis=0), [3.9, 1.9], atol=0.06)
    assert len(stored["geometry"]["coordinates"]) == 2  # the box is a hole
    assert wait_until(
        lambda: any("map not imported" in e["message"] for e in events.on("rlutf/events"))
    )
    sub.undeclare()


def test_the_laser_pose_comes_from_tf_static(ros_bench: Bench) -> None:
    bench = ros_bench
    listener = RosListener()
    laser = np.array([0.25, 0.05, 0.1])  # 25 cm ahead: ignoring it would miss by that much
    r = _robot(bench, "/robot1", 8, humble=False, laser=laser)
    pose_key = key(0, "/robot1/amcl_pose", POSE, False)
    sub = bench.client.declare_subscriber(pose_key, listener)
    r.tf_static()
    _start(bench, [r])
    _drive([r], 20)
    assert wait_until(lambda: len(listener.on(pose_key)) >= 15)
    errors = []
    for raw, _ in listener.on(pose_key)[-5:]:
        m = TS.deserialize_cdr(raw, POSE)
        i = round((m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec - r.t0) / 1e8)
        p = m.pose.pose.position
        errors.append(math.hypot(p.x - r.truth[i, 0], p.y - r.truth[i, 1]))
    assert max(errors) < 0.05, errors
    health = json.loads(bench.service.health())
    assert health["extra"]["ros2_scans_laser_at_base"] == 0
    sub.undeclare()
