"""``rlutf demo``, the README's first command, end to end: the service in its default layout
with a simulated fleet, every robot answered, and the logs it leaves audited run by run."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from service.cores import usable_cores

pytestmark = pytest.mark.integration


def test_demo_answers_every_robot_and_its_logs_audit(tmp_path: Path) -> None:
    # piped, as in a CI log: the summary table keeps one line per robot, its id whole
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    logs = tmp_path / "logs"
    demo = [sys.executable, "-m", "service", "demo", "--robots", "3", "--duration", "4"]
    demo += ["--quiet", "--record", str(logs), "--store", str(tmp_path / "store")]
    done = subprocess.run(demo, env=env, capture_output=True, text=True, timeout=600, check=False)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out
    rows = re.findall(r"robot-0(\d) \S\s+(\d+) / (\d+) ", out)
    assert sorted(r[0] for r in rows) == ["1", "2", "3"], out
    for _, poses, scans in rows:
        assert int(scans) >= 35 and int(poses) >= 0.9 * int(scans), out
    assert "WARNING" not in out and "rejected 0" in out, out
    assert "instance demo-p" not in out, out  # the processes' own start lines are logs, not news
    files = sorted(logs.glob("*.mcap"))
    cores = usable_cores()
    if cores >= 2:  # the layout of processes: a run per process
        assert f"{cores} service processes behind the router" in out, out
        writers = {re.sub(r"-\d{8}T\d{6}Z-\d+\.mcap$", "", f.name) for f in files}
        assert writers == {f"rlutf-demo-p{k}" for k in range(cores)}, files
    audit = [sys.executable, "-m", "service", "replay", *map(str, files)]
    audit += ["--out", str(tmp_path / "replayed"), "--no-foxglove", "--quiet"]
    done = subprocess.run(audit, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
