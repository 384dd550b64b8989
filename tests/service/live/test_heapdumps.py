"""The tracemalloc diagnosis: a process snapshots its allocations on SIGUSR2, and what grew
between two snapshots is found at the line that allocated it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from service.live.heapdumps import ENV_DIR, ENV_FRAMES, grown, snapshots

GROWS = """
import os, signal, time
from service.live.heapdumps import install_from_env
assert install_from_env()
kept = []
os.kill(os.getpid(), signal.SIGUSR2)
for _ in range(2000):
    kept.append(bytearray(1000))  # the line that grows
os.kill(os.getpid(), signal.SIGUSR2)
time.sleep(0.1)
print(os.getpid())
"""


def _run(tmp_path: Path, frames: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, ENV_FRAMES: frames, ENV_DIR: str(tmp_path)}
    return subprocess.run(
        [sys.executable, "-c", GROWS],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_two_snapshots_name_the_line_that_grew(tmp_path: Path) -> None:
    done = _run(tmp_path, "1")
    assert done.returncode == 0, done.stderr
    found = snapshots(tmp_path, int(done.stdout))
    assert [p.name.rsplit("-", 1)[1] for p in found] == ["1.tracemalloc", "2.tracemalloc"]
    total, rows = grown(found[0], found[1])
    assert total >= 2000
    assert rows[0].where == "<string>:8" and rows[0].kb >= 2000 and rows[0].blocks >= 2000


def test_a_bad_frame_count_traces_nothing(tmp_path: Path) -> None:
    done = _run(tmp_path, "lots")
    assert done.returncode != 0 and "AssertionError" in done.stderr
    assert not list(tmp_path.iterdir())
