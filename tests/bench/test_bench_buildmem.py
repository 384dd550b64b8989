"""bench.buildmem writes a posed ROS 2 bag and an rlutf log of one simulated robot and builds a
map from each in a fresh process."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from bench.buildmem import POSE_TOPIC, SCAN_TOPIC, make_bag, render
from service.ros2.bags import scans_with_poses


def test_the_bag_holds_a_pose_at_every_scan(tmp_path: Path) -> None:
    bag = make_bag(tmp_path, 12)
    assert len(list(scans_with_poses(bag, SCAN_TOPIC, POSE_TOPIC))) == 12


def test_render_builds_a_map_from_each_recording() -> None:
    text = render(argparse.Namespace(scans="40,80"))
    rows = [line for line in text.splitlines() if re.match(r"\| \d", line)]
    assert [int(r.split("|")[1]) for r in rows] == [40, 80], text
    assert all(float(r.split("|")[c]) > 50 for r in rows for c in (2, 4)), text  # peak MB
