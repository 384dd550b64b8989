"""A bag whose LaserScans say ``range_max: inf`` (a driver's "no limit") replays and builds a
map; a bag none of whose scans is valid is refused with the reason, not "no valid scan"."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from ros_client import TS, initialpose_msg, odom_msg, scan_msg

from rlutf.motion import relative
from rlutf.sim import make_building, make_trajectory
from service.cli.main import main
from service.logs.replay import replay

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 30


def _bag(path: Path, truth: np.ndarray, range_max: float, range_min: float | None = None) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    rng = np.random.default_rng(2)
    odom = np.array([relative(np.array([1.0, -2.0, 0.4]), p) for p in truth])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        oc = w.add_connection("/robot1/odom", "nav_msgs/msg/Odometry", typestore=TS)
        pc = w.add_connection(
            "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            w.write(oc, t, TS.serialize_cdr(odom_msg(odom[i], t), "nav_msgs/msg/Odometry"))
            m = scan_msg(WORLD, truth[i], t + 5_000_000, rng)
            m.ranges = np.where(np.isnan(m.ranges), np.float32(np.inf), m.ranges)
            m.range_max = range_max
            if range_min is not None:
                m.range_min = range_min
            w.write(sc, t + 5_000_000, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
            p = initialpose_msg(truth[i], t + 5_000_000)
            raw = TS.serialize_cdr(p, "geometry_msgs/msg/PoseWithCovarianceStamped")
            w.write(pc, t + 6_000_000, raw)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = tmp_path_factory.mktemp("rangemax")
    truth = make_trajectory(WORLD, np.random.default_rng(7), STEPS)
    (d / "m1.json").write_text(
        json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}), encoding="utf-8"
    )
    return {"dir": d, "truth": truth}


def _replay(d: Path, bag: Path, truth: np.ndarray, out: Path) -> int:
    x, y, th = (float(v) for v in truth[0])
    args = ["replay", str(bag), "--ros2", "--map", str(d / "m1.json"), "--quiet"]
    args += ["--scan-topic", "/robot1/scan", "--odom-topic", "/robot1/odom"]
    return main([*args, f"--initial-pose={x!r},{y!r},{th!r}", "--out", str(out)])


def test_a_bag_whose_range_max_is_inf_replays_and_builds_a_map(world: dict, tmp_path: Path) -> None:
    """Every scan of such a bag was refused ("range_max: must be finite"): replay said "no
    valid scan on /robot1/scan", map build "no scan on /robot1/scan has a pose"."""
    d, truth = world["dir"], world["truth"]
    _bag(tmp_path / "bag", truth, math.inf)
    assert _replay(d, tmp_path / "bag", truth, tmp_path / "out.mcap") == 0
    poses = replay([tmp_path / "out.mcap"]).recorded["robot1"]
    assert len(poses) == STEPS
    err = [math.hypot(p.x - truth[i, 0], p.y - truth[i, 1]) for i, p in enumerate(poses)]
    assert max(err) < 0.05, max(err)
    # The same run with a finite range_max beyond every wall gives the same poses.
    _bag(tmp_path / "finite", truth, 1e30)
    assert _replay(d, tmp_path / "finite", truth, tmp_path / "finite.mcap") == 0
    finite = replay([tmp_path / "finite.mcap"]).recorded["robot1"]
    assert [p.payload for p in finite] == [p.payload for p in poses]
    out = tmp_path / "built.json"
    topics = ["--scan-topic", "/robot1/scan", "--pose-topic", "/robot1/amcl_pose"]
    code = main(["map", "build", str(tmp_path / "bag"), "--ros2", *topics, "--out", str(out)])
    assert code == 0
    assert json.loads(out.read_text())["geometry"]["type"] in ("Polygon", "MultiPolygon")


def test_a_bag_with_no_valid_scan_says_why(
    world: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d, truth = world["dir"], world["truth"]
    _bag(tmp_path / "bag", truth, 10.0, range_min=20.0)  # range_min above range_max
    assert _replay(d, tmp_path / "bag", truth, tmp_path / "out.mcap") == 2
    err = capsys.readouterr().err
    assert "no valid scan on /robot1/scan" in err and f"{STEPS} scans refused" in err, err
    assert "range_max" in err, err
    topics = ["--scan-topic", "/robot1/scan", "--pose-topic", "/robot1/amcl_pose"]
    out = ["--out", str(tmp_path / "built.json")]
    assert main(["map", "build", str(tmp_path / "bag"), "--ros2", *topics, *out]) == 2
    err = capsys.readouterr().err
    assert "has a pose on /robot1/amcl_pose" in err and f"{STEPS} scans refused" in err, err
    assert "range_max" in err, err
