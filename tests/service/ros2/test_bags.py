"""rosbag2 in and out: a bag of a simulated run replays to the poses of the run's JSON log."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, initialpose_msg, odom_msg, quat, scan_msg, tf_msg, yaw
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

from rlutf.motion import compose, interpolate, relative
from rlutf.sim import make_building, make_trajectory
from schemas import SCHEMA_NAMES, InitialPose, LaserScan, Map, Odometry, PoseEstimate, encode
from service.cli.main import main
from service.keys import Keys
from service.logs.mcapfile import LogWriter, Record
from service.logs.replay import replay
from service.maps.mapimport import build_grid
from service.ros2 import convert
from service.ros2.bags import BagError, scans_with_poses

T0 = 1_732_300_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 40
ODOM_ORIGIN = np.array([2.0, -1.0, 0.7])


def _run(seed: int = 3) -> tuple[np.ndarray, np.ndarray, list]:
    rng = np.random.default_rng(seed)
    truth = make_trajectory(WORLD, rng, STEPS)
    odom = np.array([relative(ODOM_ORIGIN, p) for p in truth])
    scans = [scan_msg(WORLD, truth[i], T0 + i * 100_000_000 + 5_000_000, rng) for i in range(STEPS)]
    return truth, odom, scans


def _stamps(i: int) -> tuple[int, int]:
    """Receive times of odometry and scan ``i`` (the scan 5 ms after its odometry)."""
    t = T0 + i * 100_000_000
    return t, t + 5_000_000


def _write_bag(
    path: Path, odom: np.ndarray, scans: list, with_poses: np.ndarray | None = None
) -> None:
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        oc = w.add_connection("/robot1/odom", "nav_msgs/msg/Odometry", typestore=TS)
        pc = None
        if with_poses is not None:
            pc = w.add_connection(
                "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
            )
        for i in range(STEPS):
            t_odom, t_scan = _stamps(i)
            w.write(
                oc, t_odom, TS.serialize_cdr(odom_msg(odom[i], t_odom), "nav_msgs/msg/Odometry")
            )
            w.write(sc, t_scan, TS.serialize_cdr(scans[i], "sensor_msgs/msg/LaserScan"))
            if pc is not None and with_poses is not None:
                m = initialpose_msg(with_poses[i], t_scan)
                w.write(
                    pc, t_scan, TS.serialize_cdr(m, "geometry_msgs/msg/PoseWithCovarianceStamped")
                )


def _f32(v: float) -> float:
    return float(np.float32(v))  # sensor_msgs/LaserScan's angles and limits are float32


def _write_json_log(path: Path, truth: np.ndarray, odom: np.ndarray, scans: list) -> None:
    """The same run as a JSON robot sends it: the numbers its ROS messages carry.

    Ranges, angles and limits are float32, as LaserScan has them; the heading is the one the
    odometry's quaternion gives (``yaw(quat(theta))`` differs from ``theta`` in the last bit,
    and the search then differs by ~1e-7 m).
    """
    keys = Keys()
    m = Map(map_id="m1", version=1, geometry=WORLD.to_geojson())
    with open(path, "wb") as f:
        w = LogWriter(f, None)
        w.write(Record(keys.map("m1"), "rlutf.Map", encode(m), T0 - 2, T0 - 2))
        for i in range(STEPS):
            t_odom, t_scan = _stamps(i)
            heading = yaw(quat(odom[i, 2]))
            o = Odometry(stamp_ns=t_odom, x=odom[i, 0], y=odom[i, 1], theta=heading)
            w.write(
                Record(
                    keys.robot("robot1", "odom"), SCHEMA_NAMES[Odometry], encode(o), t_odom, t_odom
                )
            )
            if i == 0:
                ip = InitialPose(
                    stamp_ns=t_scan, map_id="m1", x=truth[0, 0], y=truth[0, 1], theta=truth[0, 2]
                )
                w.write(
                    Record(
                        keys.robot("robot1", "initialpose"),
                        SCHEMA_NAMES[InitialPose],
                        encode(ip),
                        t_scan - 1,
                        t_scan,
                    )
                )
            s = scans[i]
            ls = LaserScan(
                stamp_ns=t_scan,
                angle_min=_f32(s.angle_min),
                angle_increment=_f32(s.angle_increment),
                range_min=_f32(s.range_min),
                range_max=_f32(s.range_max),
                ranges=[float(r) if math.isfinite(r) else None for r in s.ranges.tolist()],
            )
            w.write(
                Record(
                    keys.robot("robot1", "scan"),
                    SCHEMA_NAMES[LaserScan],
                    encode(ls),
                    t_scan,
                    t_scan,
                )
            )
        w.finish()


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = tmp_path_factory.mktemp("bags")
    truth, odom, scans = _run()
    _write_bag(d / "bag", odom, scans)
    _write_json_log(d / "json.mcap", truth, odom, scans)
    (d / "m1.json").write_text(
        json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}), encoding="utf-8"
    )
    return {"dir": d, "truth": truth, "odom": odom}


def test_a_bag_replays_to_the_poses_of_the_json_log_of_the_same_run(run: dict) -> None:
    d, truth = run["dir"], run["truth"]
    x, y, th = (float(v) for v in truth[0])
    code = main(
        [
            "replay",
            str(d / "bag" / "bag.mcap"),  # a bare .mcap
            "--ros2",
            "--map",
            str(d / "m1.json"),
            f"--initial-pose={x!r},{y!r},{th!r}",  # "=": the numbers may start with "-"
            "--scan-topic",
            "/robot1/scan",
            "--odom-topic",
            "/robot1/odom",
            "--out",
            str(d / "from_bag.mcap"),
            "--ros2-out",
            str(d / "poses_bag"),
            "--plot",
            str(d / "plots"),
            "--quiet",
        ]
    )
    assert code == 0
    assert not (d / "from_bag.mcap.inputs.mcap").exists()
    # One bag is one run: its plot goes into the folder itself, as for any one run.
    assert [p.name for p in (d / "plots").iterdir()] == ["robot1.png"]
    from_json = replay([d / "json.mcap"], d / "from_json.mcap").recomputed["robot1"]
    from_bag = replay([d / "from_bag.mcap"]).recorded["robot1"]
    assert len(from_bag) == len(from_json) == STEPS
    assert [p.stamp_ns for p in from_bag] == [p.stamp_ns for p in from_json]
    # Same poses, bit for bit: the CDR path loses nothing the JSON path keeps.
    assert [p.payload for p in from_bag] == [p.payload for p in from_json]
    err = [math.hypot(p.x - truth[i, 0], p.y - truth[i, 1]) for i, p in enumerate(from_bag)]
    assert max(err) < 0.05
    # The bag out: amcl_pose is the pose, map -> odom composed with odom -> base is the pose.
    with AnyReader([d / "poses_bag"], default_typestore=TS) as r:
        got: dict[str, list] = {}
        for conn, _t, raw in r.messages():
            got.setdefault(conn.topic, []).append(r.deserialize(raw, conn.msgtype))
    assert set(got) == {"/robot1/amcl_pose", "/robot1/tf"}
    poses = got["/robot1/amcl_pose"]
    assert len(poses) == STEPS and len(got["/robot1/tf"]) == STEPS
    for i, (m, tf) in enumerate(zip(poses, got["/robot1/tf"], strict=True)):
        pe: PoseEstimate = from_bag[i]
        assert (m.pose.pose.position.x, m.pose.pose.position.y) == (pe.x, pe.y)
        t = tf.transforms[0]
        assert (t.header.frame_id, t.child_frame_id) == ("map", "odom")
        m_o = np.array(
            [t.transform.translation.x, t.transform.translation.y, yaw(t.transform.rotation)]
        )
        o = run["odom"]
        # odometry at the scan's stamp, 5 ms after reading i
        at = interpolate(o[i], o[i + 1], 0.05) if i + 1 < STEPS else o[i]
        base = compose(m_o, at)
        assert np.allclose(base[:2], [pe.x, pe.y], atol=1e-9)


def test_bag_errors_are_one_line_and_exit_2(run: dict, capsys: pytest.CaptureFixture[str]) -> None:
    d = run["dir"]
    base = ["replay", str(d / "bag"), "--ros2", "--out", str(d / "x.mcap"), "--quiet"]
    assert main(base) == 2
    assert "--map" in capsys.readouterr().err
    assert main([*base, "--map", str(d / "m1.json"), "--scan-topic", "/nope"]) == 2
    assert "no topic /nope" in capsys.readouterr().err
    topics = ["--scan-topic", "/robot1/scan", "--odom-topic", "/robot1/odom"]
    assert main([*base, "--map", str(d / "m1.json"), *topics]) == 2
    assert "no initial pose" in capsys.readouterr().err
    assert main([*base, "--map", "unknown-map", "--store", str(d / "store")]) == 2
    assert "no such map" in capsys.readouterr().err


def test_map_build_from_a_bag_with_poses(run: dict, tmp_path: Path) -> None:
    d = run["dir"]
    truth, odom, scans = _run(seed=4)
    _write_bag(tmp_path / "posed", odom, scans, with_poses=truth)
    out = tmp_path / "built.json"
    code = main(
        [
            "map",
            "build",
            str(tmp_path / "posed"),
            "--ros2",
            "--scan-topic",
            "/robot1/scan",
            "--pose-topic",
            "/robot1/amcl_pose",
            "--id",
            "built",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    built = json.loads(out.read_text())
    assert built["map_id"] == "built" and built["geometry"]["type"] in ("Polygon", "MultiPolygon")
    del d


def _write_posed(path: Path, scans: list, poses: dict[int, np.ndarray]) -> None:
    """Scans ``0..STEPS-1`` and, for the steps in ``poses``, a pose at the scan's stamp."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        pc = w.add_connection(
            "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        for i in range(STEPS):
            t_scan = _stamps(i)[1]
            w.write(sc, t_scan, TS.serialize_cdr(scans[i], "sensor_msgs/msg/LaserScan"))
            if i in poses:
                m = initialpose_msg(poses[i], t_scan)
                w.write(
                    pc, t_scan, TS.serialize_cdr(m, "geometry_msgs/msg/PoseWithCovarianceStamped")
                )


def test_a_bags_scans_take_the_pose_at_their_stamp_and_are_read_as_they_come(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Scans outside the poses' span, or over half a second from any pose, are left out; the
    others take the pose interpolated at their stamp. The scans are given as the bag is read
    (poses first), so ``build_grid`` can read them twice instead of holding them."""
    truth, _odom, scans = _run(seed=6)
    posed = {i: truth[i] for i in [*range(10, 15), *range(26, 30)]}  # scans 100 ms apart
    _write_posed(tmp_path / "bag", scans, posed)
    got = list(scans_with_poses(tmp_path / "bag", "/robot1/scan", "/robot1/amcl_pose"))
    # 10-14 posed; 15-19 within 0.5 s of 14; 20 is 0.6 s from 14 and from 26; 21-25 within
    # 0.5 s of 26; 26-29 posed; before 10 and after 29: outside the span.
    kept = [*range(10, 20), *range(21, 30)]
    assert len(got) == len(kept)
    for i, (pose, ranges, angles, range_max) in zip(kept, got, strict=True):
        expected = interpolate(truth[14], truth[26], (i - 14) / 12) if 14 < i < 26 else truth[i]
        assert np.allclose(pose, expected, atol=1e-9), i
        assert len(ranges) == len(angles) == len(scans[i].ranges)
        assert range_max == pytest.approx(scans[i].range_max)
    # Given as they are read: the first posed scan (the 11th of the bag) before the others.
    converted: list[int] = []
    real = convert.laser_scan

    def counted(raw: bytes, **kwargs: object) -> object:
        converted.append(1)
        return real(raw, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(convert, "laser_scan", counted)
    first = scans_with_poses(tmp_path / "bag", "/robot1/scan", "/robot1/amcl_pose")
    assert np.array_equal(next(first)[0], got[0][0])
    assert len(converted) == 11
    first.close()
    monkeypatch.undo()
    # The scans read anew each time give the grid the scans held give.
    read = build_grid(
        lambda: scans_with_poses(tmp_path / "bag", "/robot1/scan", "/robot1/amcl_pose")
    )
    held = build_grid(got)
    assert np.array_equal(read.data, held.data) and read.origin == held.origin
    # A bag without the pose topic has no posed scan (and is not read whole for it).
    with pytest.raises(BagError, match=r"/nope \(--pose-topic\) is not in the bag"):
        list(scans_with_poses(tmp_path / "bag", "/robot1/scan", "/nope"))


def test_a_damaged_bag_is_one_line_that_says_so(
    run: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rosbags raises whatever the damage makes it raise (here an ``OverflowError`` from a
    record length read from zeros): a BagError naming the bag, not "unexpected error"."""
    truth, odom, scans = _run(seed=4)
    _write_bag(tmp_path / "posed", odom, scans, with_poses=truth)
    (data,) = (tmp_path / "posed").glob("*.mcap")
    raw = bytearray(data.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 2000] = bytes(2000)
    data.write_bytes(bytes(raw))
    topics = ["--scan-topic", "/robot1/scan", "--pose-topic", "/robot1/amcl_pose"]
    out = ["--out", str(tmp_path / "built.json")]
    assert main(["map", "build", str(tmp_path / "posed"), "--ros2", *topics, *out]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'posed'}: damaged: " in err and "mcap recover" in err, err
    assert "unexpected error" not in err and len(err.strip().splitlines()) == 1, err
    x, y, th = (float(v) for v in truth[0])
    args = ["replay", str(tmp_path / "posed"), "--ros2", "--map", str(run["dir"] / "m1.json")]
    args += ["--scan-topic", "/robot1/scan", "--odom-topic", "/robot1/odom"]
    args += [f"--initial-pose={x!r},{y!r},{th!r}", "--quiet"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert ": damaged: " in err and "unexpected error" not in err, err


def test_the_laser_pose_comes_from_the_bags_tf_static(run: dict, tmp_path: Path) -> None:
    truth, odom = run["truth"], run["odom"]
    laser = np.array([0.3, -0.05, -0.2])
    rng = np.random.default_rng(5)
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        tc = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
        sc = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        oc = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TS)
        tf = tf_msg(laser, T0, "base_footprint", "laser")
        w.write(tc, T0 - 10, TS.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
        for i in range(STEPS):
            t_odom, t_scan = _stamps(i)
            w.write(
                oc, t_odom, TS.serialize_cdr(odom_msg(odom[i], t_odom), "nav_msgs/msg/Odometry")
            )
            m = scan_msg(WORLD, compose(truth[i], laser), t_scan, rng, "laser")
            w.write(sc, t_scan, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
    x, y, th = (float(v) for v in truth[0])
    args = ["replay", str(tmp_path / "bag"), "--ros2", "--map", str(run["dir"] / "m1.json")]
    args += [f"--initial-pose={x!r},{y!r},{th!r}", "--out", str(tmp_path / "out.mcap"), "--quiet"]
    assert main(args) == 0
    poses = replay([tmp_path / "out.mcap"]).recorded["robot"]
    assert len(poses) == STEPS
    err = [math.hypot(p.x - truth[i, 0], p.y - truth[i, 1]) for i, p in enumerate(poses)]
    assert max(err) < 0.05, max(err)
