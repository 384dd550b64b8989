"""A rosbag2 recording given to ``rlutf replay`` without ``--ros2`` is named, not audited.

An operator with a ROS 2 fleet records ``ros2 bag record -s mcap /scan /odom`` and tries
``rlutf replay`` on it: it is an MCAP file, but none of its channels carries an rlutf message.
The replay found no input in it and said ``audit: passed``-like success (exit 0, "nothing to
audit"); an audit that read nothing must not pass.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer as McapWriter
from ros_client import TS, odom_msg, scan_msg
from rosbags.rosbag2 import StoragePlugin, Writer

from rlutf.sim import make_building
from schemas import Map, encode
from service.cli.main import main

T0 = 1_732_300_000_000_000_000


def _bag(path: Path) -> Path:
    """A rosbag2 (MCAP storage) of one robot's scans and odometry, written by rosbags."""
    world = make_building(np.random.default_rng(5))
    rng = np.random.default_rng(1)
    pose = np.array([2.0, 2.0, 0.0])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        scans = w.add_connection("/amr7/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        odom = w.add_connection("/amr7/odom", "nav_msgs/msg/Odometry", typestore=TS)
        for i in range(3):
            t = T0 + i * 100_000_000
            w.write(odom, t, TS.serialize_cdr(odom_msg(pose, t), "nav_msgs/msg/Odometry"))
            scan = scan_msg(world, pose, t, rng)
            w.write(scans, t, TS.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
    return path


def test_replay_of_a_rosbag_without_ros2_names_it_and_the_command_that_reads_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _bag(tmp_path / "bag")
    for given in (bag, next(bag.glob("*.mcap"))):  # the folder, or its .mcap file
        assert main(["replay", str(given), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "a ROS 2 recording" in err and "not an rlutf log" in err, err
        assert f"rlutf replay --ros2 {bag} --map ID" in err, err
        assert "--scan-topic /amr7/scan --odom-topic /amr7/odom" in err, err
    # rlutf log info describes it (it is an MCAP file) and says the same
    assert main(["log", "info", str(next(bag.glob("*.mcap")))]) == 0
    out = capsys.readouterr().out
    assert "/amr7/scan" in out and f"rlutf replay --ros2 {bag} --map ID" in out, out


def test_another_tools_mcap_is_not_audited_as_an_empty_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "camera.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        schema = w.register_schema("foxglove.CompressedImage", "jsonschema", b"{}")
        channel = w.register_channel("/camera", "json", schema)
        w.add_message(channel, log_time=T0, publish_time=T0, data=b"{}")
        w.finish()
    assert main(["replay", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "not an rlutf log" in err and "/camera (foxglove.CompressedImage)" in err, err


def test_a_bag_whose_metadata_rosbags_cannot_read_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rosbags reads a bag folder's ``metadata.yaml`` when it opens the bag, not when it is
    made: its error came out as an 'unexpected error: AnyReaderError' to report."""
    bag = _bag(tmp_path / "bag")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [1, 2]\n")
    site = tmp_path / "m1.json"
    world = make_building(np.random.default_rng(5))
    site.write_bytes(encode(Map(map_id="m1", version=1, geometry=world.to_geojson())))
    argv = ["replay", "--ros2", str(bag), "--map", str(site), "--initial-pose=2,2,0"]
    assert main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{bag}: not a readable rosbag2 recording" in err, err
    assert "unexpected error" not in err
