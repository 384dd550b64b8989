"""bench.replaymem makes logs with poses from the simulated fleet and audits each in a fresh
process, as ``rlutf replay`` and keeping every pose; each audit must pass."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from bench.replaymem import make_log, render
from service.logs.mcapread import LogFile


def test_the_log_holds_the_fleets_inputs_and_a_pose_per_scan(tmp_path: Path) -> None:
    log, poses = make_log(tmp_path, robots=2, steps=15)
    assert poses == 2 * 15
    with LogFile(log) as lf:
        kinds = [r.schema_name for r in lf.messages()]
    assert kinds.count("rlutf.LaserScan") == kinds.count("rlutf.PoseEstimate") == 30
    assert kinds.count("rlutf.Odometry") == 2 * 16 and kinds.count("rlutf.Map") == 1


def test_render_audits_each_length_in_a_fresh_process() -> None:
    text = render(argparse.Namespace(robots=2, steps="10,20"))
    rows = [line for line in text.splitlines() if re.match(r"\| \d", line)]
    assert [int(r.split("|")[2]) for r in rows] == [20, 40], text  # poses per log
    assert all(float(r.split("|")[c]) > 50 for r in rows for c in (4, 6, 8)), text  # peak MB
    assert "MB per million poses" in text
