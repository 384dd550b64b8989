"""``rlutf replay``'s bag flags: given without ``--ros2`` they were ignored in silence
(``--ros2-out`` wrote nothing, exit 0); a ``--ros2-out`` that exists was refused only once the
whole replay was done. Both are refused before any work, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, initialpose_msg, odom_msg, scan_msg

from rlutf.sim import make_building, make_trajectory
from service.cli.main import main

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 10


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from rosbags.rosbag2 import StoragePlugin, Writer

    d = tmp_path_factory.mktemp("flags")
    truth = make_trajectory(WORLD, np.random.default_rng(2), STEPS)
    rng = np.random.default_rng(3)
    with Writer(d / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        oc = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TS)
        ic = w.add_connection(
            "/initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        ip = initialpose_msg(truth[0], T0)
        w.write(ic, T0, TS.serialize_cdr(ip, "geometry_msgs/msg/PoseWithCovarianceStamped"))
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            w.write(oc, t, TS.serialize_cdr(odom_msg(truth[i], t), "nav_msgs/msg/Odometry"))
            m = scan_msg(WORLD, truth[i], t + 1, rng)
            w.write(sc, t + 1, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
    (d / "m1.json").write_text(
        json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}), encoding="utf-8"
    )
    base = ["replay", str(d / "bag"), "--ros2", "--map", str(d / "m1.json"), "--quiet"]
    assert main([*base, "--out", str(d / "log.mcap")]) == 0  # an rlutf log of the run
    return {"dir": d, "log": d / "log.mcap"}


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--ros2-out", "{dir}/poses_bag"], "--ros2-out"),
        (["--map", "m1", "--initial-pose=1,2,0"], "--map, --initial-pose"),
        (["--scan-topic", "/robot1/scan", "--odom-tf"], "--scan-topic, --odom-tf"),
    ],
)
def test_bag_flags_without_ros2_are_refused(
    bag: dict[str, Path], capsys: pytest.CaptureFixture[str], flags: list[str], named: str
) -> None:
    flags = [f.format(dir=bag["dir"]) for f in flags]
    assert main(["replay", str(bag["log"]), "--quiet", *flags]) == 2
    err = capsys.readouterr().err
    assert f"rlutf replay: {named}: only read with --ros2" in err, err
    assert not (bag["dir"] / "poses_bag").exists()
    # Without them, the log replays and passes its audit.
    assert main(["replay", str(bag["log"]), "--quiet"]) == 0


def test_an_existing_ros2_out_is_refused_before_the_replay(
    bag: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    d = bag["dir"]
    (d / "taken").mkdir()
    args = ["replay", str(d / "bag"), "--ros2", "--map", str(d / "m1.json"), "--quiet"]
    assert main([*args, "--ros2-out", str(d / "taken")]) == 2
    captured = capsys.readouterr()
    assert f"--ros2-out {d / 'taken'}: exists already" in captured.err, captured.err
    assert "replayed" not in captured.out, captured.out  # refused before the replay
    assert main([*args, "--ros2-out", str(d / "fresh")]) == 0
    assert (d / "fresh" / "metadata.yaml").is_file()
    # a folder that does not exist is refused as --out's is (it was made)
    assert main([*args, "--ros2-out", str(d / "missing" / "poses")]) == 2
    captured = capsys.readouterr()
    assert f"the folder {d / 'missing'} does not exist" in captured.err, captured.err
    assert not (d / "missing").exists()


def test_a_robot_id_replay_cannot_use_is_refused_with_the_fix(
    bag: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--robot 'a b'`` replayed every input to nothing (0 poses, 0 rejected, exit 0); a bag
    of a nested namespace (``/site/r7/scan``) was sent to the live service's settings."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    d = bag["dir"]
    args = ["replay", "--ros2", "--map", str(d / "m1.json"), "--quiet"]
    assert main([*args, str(d / "bag"), "--robot", "a b"]) == 2
    assert "--robot 'a b': not a robot id" in capsys.readouterr().err
    # The same run under /site/r7: its namespace is no robot id.
    with (
        Reader(d / "bag") as r,
        Writer(tmp_path / "nested", version=9, storage_plugin=StoragePlugin.MCAP) as w,
    ):
        conns = {
            c.id: w.add_connection(f"/site/r7{c.topic}", c.msgtype, typestore=TS)
            for c in r.connections
        }
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
    topics = ["--scan-topic", "/site/r7/scan", "--odom-topic", "/site/r7/odom"]
    assert main([*args, str(tmp_path / "nested"), *topics]) == 2
    err = capsys.readouterr().err
    assert "namespace '/site/r7' is not a robot id" in err and "--robot ID" in err, err
    assert "ros2.robots" not in err, err
    assert main([*args, str(tmp_path / "nested"), *topics, "--robot", "r7"]) == 0
