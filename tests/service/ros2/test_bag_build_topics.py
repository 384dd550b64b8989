"""``rlutf map build BAG --ros2`` names a scan or pose topic the bag lacks, or that carries
another type, with the topics that would do: it said "no scan on /scan has a pose on
/amcl_pose" of a namespaced bag, whose topics are /robot1/scan and /robot1/amcl_pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, initialpose_msg, scan_msg

from rlutf.sim import make_building, make_trajectory
from service.cli.main import main

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 10


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer

    d = tmp_path_factory.mktemp("topics")
    truth = make_trajectory(WORLD, np.random.default_rng(2), STEPS)
    rng = np.random.default_rng(3)
    with Writer(d / "bag", version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        pc = w.add_connection(
            "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            m = scan_msg(WORLD, truth[i], t, rng)
            w.write(sc, t, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
            p = initialpose_msg(truth[i], t)
            raw = TS.serialize_cdr(p, "geometry_msgs/msg/PoseWithCovarianceStamped")
            w.write(pc, t + 1, raw)
    return d / "bag"


@pytest.mark.parametrize(
    ("flags", "said"),
    [
        ([], "/scan (--scan-topic) is not in the bag; give --scan-topic /robot1/scan"),
        (
            ["--scan-topic", "/robot1/scan"],
            "/amcl_pose (--pose-topic) is not in the bag; give --pose-topic /robot1/amcl_pose",
        ),
        (
            ["--scan-topic", "/robot1/scan", "--pose-topic", "/robot1/scan"],
            "/robot1/scan (--pose-topic) carries sensor_msgs/msg/LaserScan, not "
            "geometry_msgs/msg/PoseWithCovarianceStamped or nav_msgs/msg/Odometry; give "
            "--pose-topic /robot1/amcl_pose",
        ),
    ],
)
def test_a_topic_the_bag_lacks_is_named_with_the_ones_it_has(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], said: str
) -> None:
    out = ["--out", str(tmp_path / "built.json")]
    assert main(["map", "build", str(bag), "--ros2", *flags, *out]) == 2
    err = capsys.readouterr().err
    assert said in err, err
    topics = ["--scan-topic", "/robot1/scan", "--pose-topic", "/robot1/amcl_pose"]
    assert main(["map", "build", str(bag), "--ros2", *topics, *out]) == 0
