"""``rlutf replay`` interrupted (Ctrl-C): exit 130, said on stderr, no output log left.

Before, a replay stopped by Ctrl-C exited 130 in silence: what it had printed (a run's
heading, a progress bar) was all an auditor saw, with no word that the audit had not finished
and given no verdict.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcaplog_fixtures import simulated_inputs, write_log

pytestmark = pytest.mark.integration

#: Runs the command after it with SIGINT's default, as one typed in a terminal (a test run from
#: a background job hands its children SIGINT ignored).
_AS_A_TERMINAL = (
    sys.executable,
    "-c",
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
    "os.execv(sys.argv[1], sys.argv[1:])",
)


def test_an_interrupted_replay_says_so_and_leaves_no_output(tmp_path: Path) -> None:
    robots = tuple(f"r{i}" for i in range(6))
    log = write_log(tmp_path / "in.mcap", simulated_inputs(robots, steps=600, beams=90))
    out = tmp_path / "out.mcap"
    part = tmp_path / "out.mcap.part"
    cmd = (sys.executable, "-m", "service", "replay", str(log), "--out", str(out), "--quiet")
    proc = subprocess.Popen(
        (*_AS_A_TERMINAL, *cmd),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        end = time.monotonic() + 120
        while not part.exists() and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.01)
        assert part.exists(), "the replay ended before it was interrupted"
        time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C: the whole group
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130
    text = err.decode()
    assert "rlutf replay: interrupted" in text
    assert "no verdict" in text
    assert "Traceback" not in text
    assert not part.exists() and not out.exists()
