"""A rosbag2 of the sqlite3 storage (a folder with metadata.yaml and a .db3, ROS 2's default
before Iron) given without ``--ros2`` is named as a bag, with the commands that read it, as an
MCAP bag is: it was "a folder with no log file (*.mcap) in it" or "not an MCAP file"."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, scan_msg

from rlutf.sim import make_building
from service.cli.main import main

WORLD = make_building(np.random.default_rng(21))


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = tmp_path_factory.mktemp("sqlite") / "bag"
    with Writer(path, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        sc = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        m = scan_msg(
            WORLD, np.array([5.0, 5.0, 0.0]), 1_765_000_000_000_000_000, np.random.default_rng(1)
        )
        w.write(sc, 1_765_000_000_000_000_000, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
    return path


@pytest.mark.parametrize(
    "argv",
    [
        ["replay", "{bag}", "--quiet"],
        ["map", "build", "{bag}", "--out", "{tmp}/built.json"],
        ["log", "info", "{bag}"],
    ],
)
def test_a_sqlite3_bag_folder_is_named_as_a_bag(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str]
) -> None:
    assert main([a.format(bag=bag, tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "a rosbag2 recording (metadata.yaml)" in err and "--ros2" in err, err


def test_a_db3_file_is_named_as_a_bag(bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (db3,) = bag.glob("*.db3")
    assert main(["replay", str(db3), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "a rosbag2 recording (sqlite3), which --ros2 reads" in err, err


def test_a_bag_that_is_not_there_is_said_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rosbags' "The following paths are missing: [PosixPath('...')]" was printed as it is."""
    missing = tmp_path / "nobag"
    (tmp_path / "m1.json").write_text(
        json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}), encoding="utf-8"
    )
    args = ["replay", str(missing), "--ros2", "--map", str(tmp_path / "m1.json")]
    assert main([*args, "--initial-pose=1,2,0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{missing}: no such file or folder" in err and "PosixPath" not in err, err
