"""``rlutf replay BAG --ros2`` says when a bag's scans are in a frame its ``tf_static`` does not
link to the base frame (a bag recorded without ``tf_static``): they are taken at the base, and
every pose is off by the laser's mount. It said nothing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, odom_msg, scan_msg, tf_msg

from rlutf.motion import compose, relative
from rlutf.sim import make_building, make_trajectory
from service.cli.main import main

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 20
LASER = np.array([0.2, 0.0, 0.0])


def _bag(path: Path, truth: np.ndarray, static_topic: str | None) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    rng = np.random.default_rng(1)
    odom = np.array([relative(np.array([1.0, -2.0, 0.4]), p) for p in truth])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        oc = w.add_connection("/robot1/odom", "nav_msgs/msg/Odometry", typestore=TS)
        if static_topic is not None:
            stc = w.add_connection(static_topic, "tf2_msgs/msg/TFMessage", typestore=TS)
            raw = TS.serialize_cdr(
                tf_msg(LASER, T0, "base_footprint", "laser"), "tf2_msgs/msg/TFMessage"
            )
            w.write(stc, T0 - 10, raw)
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            w.write(oc, t, TS.serialize_cdr(odom_msg(odom[i], t), "nav_msgs/msg/Odometry"))
            m = scan_msg(WORLD, compose(truth[i], LASER), t + 5_000_000, rng, "laser")
            w.write(sc, t + 5_000_000, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))


@pytest.mark.parametrize(
    ("static_topic", "said"),
    [
        (None, "(the bag has no such topic)"),
        ("/tf_static", "the bag's tf_static is on /tf_static"),
        ("/robot1/tf_static", None),
    ],
)
def test_scans_in_a_frame_tf_static_does_not_link_are_said(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    static_topic: str | None,
    said: str | None,
) -> None:
    truth = make_trajectory(WORLD, np.random.default_rng(3), STEPS)
    _bag(tmp_path / "bag", truth, static_topic)
    (tmp_path / "m1.json").write_text(
        json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}), encoding="utf-8"
    )
    x, y, th = (float(v) for v in truth[0])
    args = ["replay", str(tmp_path / "bag"), "--ros2", "--map", str(tmp_path / "m1.json")]
    args += ["--scan-topic", "/robot1/scan", "--odom-topic", "/robot1/odom", "--quiet"]
    assert main([*args, f"--initial-pose={x!r},{y!r},{th!r}"]) == 0
    out = " ".join(capsys.readouterr().out.split())  # rich wraps long lines
    if said is None:
        assert "taken at" not in out, out
        return
    assert f"{STEPS} of {STEPS} scans were taken at 'base_footprint'" in out, out
    assert "frame 'laser'" in out and "/robot1/tf_static" in out and said in out, out


def test_map_build_says_so_too_and_takes_base_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The map build from such a bag put every scan at the base in silence, and had no
    --base-frame for a robot whose poses are of base_link (tf_static: base_link -> laser)."""
    from ros_client import initialpose_msg
    from rosbags.rosbag2 import StoragePlugin, Writer

    truth = make_trajectory(WORLD, np.random.default_rng(3), STEPS)
    rng = np.random.default_rng(1)
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        pc = w.add_connection(
            "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        stc = w.add_connection("/robot1/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
        raw = TS.serialize_cdr(tf_msg(LASER, T0, "base_link", "laser"), "tf2_msgs/msg/TFMessage")
        w.write(stc, T0 - 10, raw)
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            m = scan_msg(WORLD, compose(truth[i], LASER), t, rng, "laser")
            w.write(sc, t, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
            p = initialpose_msg(truth[i], t)
            w.write(pc, t, TS.serialize_cdr(p, "geometry_msgs/msg/PoseWithCovarianceStamped"))
    args = ["map", "build", str(tmp_path / "bag"), "--ros2", "--scan-topic", "/robot1/scan"]
    args += ["--pose-topic", "/robot1/amcl_pose", "--out", str(tmp_path / "built.json")]
    assert main(args) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert f"warning: {STEPS} of {STEPS} scans were taken at 'base_footprint'" in err, err
    assert main([*args, "--base-frame", "base_link"]) == 0
    assert "taken at" not in capsys.readouterr().err
