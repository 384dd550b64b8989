"""``rlutf map build BAG --ros2`` puts each scan at the laser, from the bag's ``tf_static``, as
replay does: a laser mounted ahead of the base smeared every wall of the map built into two."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import shapely
from ros_client import TS, initialpose_msg, scan_msg, tf_msg

from rlutf.motion import compose
from rlutf.sim import make_building, make_trajectory
from service.cli.main import main
from service.maps.mapimport import OccupancyGrid, build_grid
from service.ros2.bags import scans_with_poses

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 60
LASER = np.array([0.25, 0.05, 0.1])  # in base_link, itself 0.1 m ahead of base_footprint
BASE_LINK = np.array([0.1, 0.0, 0.0])
TOPICS = ("/robot1/scan", "/robot1/amcl_pose")


def _bag(path: Path, truth: np.ndarray, mounted: bool) -> None:
    """Poses of base_footprint on amcl_pose; scans from the laser, on /robot1/scan."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    rng = np.random.default_rng(3)
    frame = "laser" if mounted else "base_footprint"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        stc = w.add_connection("/robot1/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        pc = w.add_connection(
            "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        for parent, child, pose in (
            ("base_footprint", "base_link", BASE_LINK),
            ("base_link", "laser", LASER),
        ):
            raw = TS.serialize_cdr(tf_msg(pose, T0, parent, child), "tf2_msgs/msg/TFMessage")
            w.write(stc, T0 - 10, raw)
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            at = compose(compose(truth[i], BASE_LINK), LASER) if mounted else truth[i]
            m = scan_msg(WORLD, at, t, rng, frame)
            w.write(sc, t, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
            p = initialpose_msg(truth[i], t)
            raw = TS.serialize_cdr(p, "geometry_msgs/msg/PoseWithCovarianceStamped")
            w.write(pc, t + 1_000_000, raw)


def _walls_missed(grid: OccupancyGrid) -> float:
    """The share of the grid's occupied cells farther than 10 cm from a wall of the world."""
    rows, cols = np.nonzero(grid.occupied)
    centres = grid.cell_centres(rows, cols)
    far = shapely.distance(WORLD.geometry.boundary, shapely.points(centres)) > 0.1
    return float(np.mean(far))


def test_a_bags_scans_are_placed_at_the_laser_of_its_tf_static(tmp_path: Path) -> None:
    truth = make_trajectory(WORLD, np.random.default_rng(9), STEPS)
    _bag(tmp_path / "mounted", truth, mounted=True)
    got = list(scans_with_poses(tmp_path / "mounted", *TOPICS))
    assert len(got) == STEPS
    for i, (pose, *_rest) in enumerate(got):
        expected = compose(compose(truth[i], BASE_LINK), LASER)
        assert np.allclose(pose, expected, atol=1e-6), (i, pose, expected)
    # Its occupied cells lie on the world's walls, as those of a laser at the base do.
    mounted = build_grid(lambda: scans_with_poses(tmp_path / "mounted", *TOPICS))
    _bag(tmp_path / "at_base", truth, mounted=False)
    at_base = build_grid(lambda: scans_with_poses(tmp_path / "at_base", *TOPICS))
    assert _walls_missed(at_base) < 0.02
    assert _walls_missed(mounted) < 0.02, _walls_missed(mounted)  # 0.6 before
    # And the command builds it.
    topics = ["--scan-topic", TOPICS[0], "--pose-topic", TOPICS[1]]
    out = tmp_path / "built.json"
    assert (
        main(["map", "build", str(tmp_path / "mounted"), "--ros2", *topics, "--out", str(out)]) == 0
    )
    assert json.loads(out.read_text())["geometry"]["type"] in ("Polygon", "MultiPolygon")
