"""``rlutf map build BAG --ros2`` on a bag whose clock was set back midway (a simulation
restarted while recording): each scan takes a pose of its own span of the recording. The poses
of the two spans, stamped alike, were mixed, and half the map's walls drawn from wrong poses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import shapely
from ros_client import TS, initialpose_msg, scan_msg

from rlutf.sim import make_building, make_trajectory
from service.cli.main import main
from service.maps.mapimport import build_grid
from service.ros2.bags import scans_with_poses

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 80
RESET = 40  # from this step on, the stamps are 3 s earlier (the bag's receive times are not)
TOPICS = ("/robot1/scan", "/robot1/amcl_pose")


def _bag(path: Path, truth: np.ndarray) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    rng = np.random.default_rng(3)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection(TOPICS[0], "sensor_msgs/msg/LaserScan", typestore=TS)
        pc = w.add_connection(
            TOPICS[1], "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        for i in range(STEPS):
            received = T0 + i * 100_000_000
            stamp = received - (3_000_000_000 if i >= RESET else 0)
            m = scan_msg(WORLD, truth[i], stamp, rng)
            w.write(sc, received, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
            p = initialpose_msg(truth[i], stamp)
            raw = TS.serialize_cdr(p, "geometry_msgs/msg/PoseWithCovarianceStamped")
            w.write(pc, received + 1_000_000, raw)


def test_scans_after_a_clock_reset_take_the_poses_after_it(tmp_path: Path) -> None:
    truth = make_trajectory(WORLD, np.random.default_rng(13), STEPS)
    _bag(tmp_path / "bag", truth)
    got = list(scans_with_poses(tmp_path / "bag", *TOPICS))
    assert len(got) == STEPS
    for i, (pose, *_rest) in enumerate(got):
        assert np.allclose(pose, truth[i], atol=1e-9), (i, pose, truth[i])
    grid = build_grid(lambda: scans_with_poses(tmp_path / "bag", *TOPICS))
    rows, cols = np.nonzero(grid.occupied)
    centres = shapely.points(grid.cell_centres(rows, cols))
    far = shapely.distance(WORLD.geometry.boundary, centres) > 0.1
    assert float(np.mean(far)) < 0.02, float(np.mean(far))
    flags = ["--scan-topic", TOPICS[0], "--pose-topic", TOPICS[1]]
    out = tmp_path / "built.json"
    assert main(["map", "build", str(tmp_path / "bag"), "--ros2", *flags, "--out", str(out)]) == 0
    assert json.loads(out.read_text())["geometry"]["type"] in ("Polygon", "MultiPolygon")
