"""A bag whose odometry is in other frames than the ones given is said in ``rlutf replay
--ros2``'s output, with the flag to give; given it, the ``map`` -> odom written connects."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, odom_msg, scan_msg, tf_msg
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

from rlutf.motion import relative
from rlutf.sim import make_building, make_trajectory
from service.cli.main import main
from service.ros2.bagframes import BagOdometryFrames
from service.ros2.frames import FRAME_CHARS
from service.ros2.statictf import StaticFrames

T0 = 1_732_300_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 20
TF = "tf2_msgs/msg/TFMessage"
ODOM = "nav_msgs/msg/Odometry"


def _bag(
    path: Path, frames: tuple[str, str], on_tf: bool, topic: str = "", steps: int = STEPS
) -> np.ndarray:
    """A bag of ``/scan`` and odometry in ``frames`` (on ``/tf``, or ``/odom``; or on ``topic``)
    in its first ``steps`` steps; the truth."""
    rng = np.random.default_rng(3)
    truth = make_trajectory(WORLD, rng, STEPS)
    origin = np.array([2.0, -1.0, 0.7])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        topic = topic or ("/tf" if on_tf else "/odom")
        oc = w.add_connection(topic, TF if on_tf else ODOM, typestore=TS)
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            odom = relative(origin, truth[i])
            m = tf_msg(odom, t, *frames) if on_tf else odom_msg(odom, t, *frames)
            if i < steps:
                w.write(oc, t, TS.serialize_cdr(m, oc.msgtype))
            scan = scan_msg(WORLD, truth[i], t + 5_000_000, rng)
            w.write(sc, t + 5_000_000, TS.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
    return truth


def _replay(tmp_path: Path, bag: Path, truth: np.ndarray, *flags: str) -> list:
    """``rlutf replay BAG --ros2 --ros2-out``: the map -> odom transforms written."""
    m1 = tmp_path / "m1.json"
    m1.write_text(json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}))
    out = tmp_path / f"{bag.name}_out{len(flags)}"
    x, y, th = (float(v) for v in truth[0])
    args = ["replay", str(bag), "--ros2", "--map", str(m1), f"--initial-pose={x!r},{y!r},{th!r}"]
    args += ["--out", str(tmp_path / "poses.mcap"), "--ros2-out", str(out), "--quiet", *flags]
    assert main(args) == 0
    with AnyReader([out], default_typestore=TS) as r:
        conns = [c for c in r.connections if c.topic == "/tf"]
        return [r.deserialize(raw, TF).transforms[0] for _c, _t, raw in r.messages(conns)]


def test_odometry_in_another_frame_is_said_and_odom_frame_connects_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = _bag(tmp_path / "bag", ("wheel_odom", "base_footprint"), on_tf=False)
    written = _replay(tmp_path, tmp_path / "bag", truth)
    out = " ".join(capsys.readouterr().out.split())  # rich wraps long lines
    assert "warning: the odometry on /odom is in frame 'wheel_odom' (20 messages)" in out, out
    assert "not 'odom'" in out and "Give --odom-frame wheel_odom" in out
    assert written and {(t.header.frame_id, t.child_frame_id) for t in written} == {("map", "odom")}
    # given the bag's frame: said no more, and map -> wheel_odom written
    written = _replay(tmp_path, tmp_path / "bag", truth, "--odom-frame", "wheel_odom")
    out = " ".join(capsys.readouterr().out.split())
    assert "warning" not in out
    assert len(written) == STEPS
    assert {(t.header.frame_id, t.child_frame_id) for t in written} == {("map", "wheel_odom")}
    assert f"wrote {STEPS} amcl_pose, {STEPS} tf ->" in out, out


def test_no_odometry_on_tf_in_the_frames_given_is_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = _bag(tmp_path / "bag", ("wheel_odom", "base_footprint"), on_tf=True)
    assert _replay(tmp_path, tmp_path / "bag", truth, "--odom-tf") == []  # nothing to write
    out = " ".join(capsys.readouterr().out.split())
    for part in (
        "warning: no odometry: /tf carries wheel_odom -> base_footprint (20 times)",
        "but no odom -> base_footprint",
        "no map -> odom is written",
        "Give --odom-frame wheel_odom",
        # it said "wrote N ROS 2 messages (amcl_pose, tf)" with no tf written
        f"wrote {STEPS} amcl_pose, no tf (no odometry at the poses' stamps)",
    ):
        assert part in out, out
    written = _replay(tmp_path, tmp_path / "bag", truth, "--odom-tf", "--odom-frame", "wheel_odom")
    assert "warning" not in capsys.readouterr().out
    assert len(written) == STEPS
    assert {(t.header.frame_id, t.child_frame_id) for t in written} == {("map", "wheel_odom")}


def test_a_bag_without_the_odometrys_topic_names_the_flag_to_give(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def refused(bag: Path, *flags: str) -> str:
        m1 = tmp_path / "m1.json"
        m1.write_text(json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}))
        args = ["replay", str(bag), "--ros2", "--map", str(m1), "--initial-pose=1,1,0"]
        assert main([*args, "--quiet", "--out", str(tmp_path / "poses.mcap"), *flags]) == 2
        return " ".join(capsys.readouterr().err.split())

    # the odometry on tf only (odom -> base_footprint): --odom-tf, which then replays with it
    truth = _bag(tmp_path / "tf", ("odom", "base_footprint"), on_tf=True)
    said = refused(tmp_path / "tf")
    for part in (
        "no topic /odom to read the odometry from",
        "(topics: /scan (sensor_msgs/msg/LaserScan), /tf (tf2_msgs/msg/TFMessage))",
        "Give --odom-tf (/tf carries odom -> base_footprint)",
    ):
        assert part in said, said
    assert len(_replay(tmp_path, tmp_path / "tf", truth, "--odom-tf")) == STEPS
    # odom -> base_link: --odom-tf with the base frame it names
    _bag(tmp_path / "link", ("odom", "base_link"), on_tf=True)
    said = refused(tmp_path / "link")
    assert "Give --odom-tf --base-frame base_link (/tf carries odom -> base_link)" in said, said
    # an Odometry on another topic: that topic
    _bag(tmp_path / "wheel", ("odom", "base_footprint"), on_tf=False, topic="/wheel/odometry")
    said = refused(tmp_path / "wheel")
    assert "Give --odom-topic /wheel/odometry" in said and "--odom-tf" not in said, said
    # --odom-tf on a bag whose odometry is an Odometry
    _bag(tmp_path / "odom", ("odom", "base_footprint"), on_tf=False)
    said = refused(tmp_path / "odom", "--odom-tf")
    assert "no topic /tf to read the odometry from" in said
    assert "Give --odom-topic /odom without --odom-tf" in said, said
    # a tf with no odometry on it, and no Odometry: nothing to give
    _bag(tmp_path / "none", ("base_link", "laser"), on_tf=True)
    said = refused(tmp_path / "none")
    assert said.endswith("and no odometry elsewhere"), said


def test_an_odometry_topic_with_no_odometry_is_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = _bag(tmp_path / "bag", ("odom", "base_footprint"), on_tf=False, steps=0)
    assert _replay(tmp_path, tmp_path / "bag", truth) == []
    out = " ".join(capsys.readouterr().out.split())
    assert "warning: no odometry: /odom carries no valid nav_msgs/Odometry" in out, out
    assert "no map -> odom is written with --ros2-out" in out


def test_the_frames_seen_alone() -> None:
    static = StaticFrames()
    static.add("base_footprint", "base_link", (0.0, 0.0, 0.0))  # above: the same in the plane
    static.add("base_link", "laser", (0.2, 0.0, 0.0))
    # an Odometry of the right frames, or of base_link: nothing to say
    f = BagOdometryFrames("/odom", False, "map", "odom", "base_footprint")
    f.add(1, [("odom", "base_footprint")])
    f.add(1, [("odom", "base_link")])
    assert f.warnings(static) == []
    # an Odometry of the laser, 20 cm ahead: the map -> odom written is off by that
    f.add(1, [("odom", "laser")])
    (said,) = f.warnings(static)
    assert "'laser'" in said and "x 0.200 m" in said and "Give --base-frame laser" in said
    # on tf: the odometry found, or a map -> odom recorded beside it, are not other frames
    t = BagOdometryFrames("/tf", True, "map", "odom", "base_footprint")
    t.add(0, [("map", "odom")])
    (said,) = t.warnings(static)  # no odometry, and no other frames to name
    assert said.startswith("no odometry: /tf carries no odom -> base_footprint"), said
    t.add(0, [("odom", "base_link")])
    (said,) = t.warnings(static)
    assert "odom -> base_link (1 times)" in said and "Give --base-frame base_link" in said
    assert "map -> odom (" not in said
    t.add(1, [("odom", "base_footprint")])
    assert t.warnings(static) == []  # some odometry found: replayed with it
    # bounded, and a frame id quoted safely
    b = BagOdometryFrames("/odom", False, "map", "odom", "base_footprint", kept=3)
    for i in range(10):
        b.add(1, [(f"o{i}\nERROR forged" + "y" * 10_000, "base_footprint")])
    assert len(b.seen) == 3
    (said,) = b.warnings(static)
    assert "\n" not in said and "\\x0a" in said and len(said) < 4 * FRAME_CHARS + 1000
