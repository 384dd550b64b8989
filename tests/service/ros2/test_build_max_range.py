"""``rlutf map build --max-range M`` bounds the ranges of a bag and of MCAP logs, not only of a
CARMEN log: it was read for CARMEN alone, and a bag or a log was built with every range up to
the scanner's maximum whatever was given."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import shapely
from ros_client import TS, initialpose_msg, odom_msg, scan_msg

from rlutf.motion import relative
from rlutf.sim import make_building, make_trajectory
from service.cli.main import main

T0 = 1_765_000_000_000_000_000
WORLD = make_building(np.random.default_rng(21))
STEPS = 30
TOPICS = ["--scan-topic", "/robot1/scan"]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A bag with poses on amcl_pose, and the MCAP log its replay writes (with poses)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    d = tmp_path_factory.mktemp("maxrange")
    truth = make_trajectory(WORLD, np.random.default_rng(11), STEPS)
    odom = np.array([relative(np.array([1.0, -2.0, 0.4]), p) for p in truth])
    rng = np.random.default_rng(4)
    with Writer(d / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        sc = w.add_connection("/robot1/scan", "sensor_msgs/msg/LaserScan", typestore=TS)
        oc = w.add_connection("/robot1/odom", "nav_msgs/msg/Odometry", typestore=TS)
        pc = w.add_connection(
            "/robot1/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped", typestore=TS
        )
        for i in range(STEPS):
            t = T0 + i * 100_000_000
            w.write(oc, t, TS.serialize_cdr(odom_msg(odom[i], t), "nav_msgs/msg/Odometry"))
            m = scan_msg(WORLD, truth[i], t + 5_000_000, rng)
            w.write(sc, t + 5_000_000, TS.serialize_cdr(m, "sensor_msgs/msg/LaserScan"))
            p = initialpose_msg(truth[i], t + 5_000_000)
            raw = TS.serialize_cdr(p, "geometry_msgs/msg/PoseWithCovarianceStamped")
            w.write(pc, t + 6_000_000, raw)
    (d / "m1.json").write_text(
        json.dumps({"map_id": "m1", "version": 1, "geometry": WORLD.to_geojson()}), encoding="utf-8"
    )
    x, y, th = (float(v) for v in truth[0])
    args = ["replay", str(d / "bag"), "--ros2", "--map", str(d / "m1.json"), "--quiet"]
    args += [*TOPICS, "--odom-topic", "/robot1/odom", f"--initial-pose={x!r},{y!r},{th!r}"]
    assert main([*args, "--out", str(d / "replayed.mcap")]) == 0
    return {"bag": d / "bag", "mcap": d / "replayed.mcap"}


def _built(log: Path, out: Path, *flags: str) -> shapely.Geometry:
    args = ["map", "build", str(log), "--out", str(out), "--id", "built", "--component", "all"]
    assert main([*args, *flags]) == 0
    return shapely.geometry.shape(json.loads(out.read_text())["geometry"])


@pytest.mark.parametrize("kind", ["bag", "mcap"])
def test_max_range_bounds_the_ranges_of_bags_and_mcap_logs(
    logs: dict[str, Path], tmp_path: Path, kind: str
) -> None:
    flags = ["--ros2", *TOPICS, "--pose-topic", "/robot1/amcl_pose"] if kind == "bag" else []
    whole = _built(logs[kind], tmp_path / "whole.json", *flags)
    near = _built(logs[kind], tmp_path / "near.json", *flags, "--max-range", "1.5")
    # Beams of 1.5 m at most free less of the building: the map is smaller.
    assert near.area < 0.8 * whole.area, (near.area, whole.area)
    # A --max-range beyond the scanner's range_max (12 m) changes nothing.
    far = _built(logs[kind], tmp_path / "far.json", *flags, "--max-range", "100")
    assert json.loads((tmp_path / "far.json").read_text()) == json.loads(
        (tmp_path / "whole.json").read_text()
    )
    assert far.equals(whole)


@pytest.mark.parametrize(
    ("kind", "flags", "said"),
    [
        ("mcap", ["--pose-topic", "/robot1/amcl_pose"], "--pose-topic: not read for MCAP logs"),
        ("bag", ["--ros2", *TOPICS, "--from-map", "m1"], "--from-map: not read for a bag"),
    ],
)
def test_flags_the_log_does_not_read_are_refused(
    logs: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    kind: str,
    flags: list[str],
    said: str,
) -> None:
    """They were ignored in silence (a map built, exit 0)."""
    out = tmp_path / "built.json"
    assert main(["map", "build", str(logs[kind]), "--out", str(out), *flags]) == 2
    assert said in capsys.readouterr().err
    assert not out.exists()
