"""A split audit interrupted in its parent process stops its shares at once.

Before, a KeyboardInterrupt in the parent (a SIGINT sent to it alone: ``kill -INT``, ``timeout
-s INT``, a supervisor) left the pool's processes running, and leaving the pool waited for
every share to finish its whole audit (seconds here, hours for a day's log).
"""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import pytest
from mcaplog_fixtures import simulated_inputs, write_log

from service.logs.replay import replay, run_config
from service.logs.split import replay_split

pytestmark = pytest.mark.integration


def test_an_interrupted_split_audit_stops_its_shares(tmp_path: Path) -> None:
    robots = tuple(f"r{i}" for i in range(4))
    inputs = write_log(tmp_path / "in.mcap", simulated_inputs(robots, steps=500, beams=90))
    log = tmp_path / "log.mcap"
    replay([inputs], log, foxglove=False)
    t0 = time.monotonic()
    replay_split([log], run_config([log]), 2, min_messages=0)
    whole = time.monotonic() - t0

    def interrupt(n: int) -> None:
        raise KeyboardInterrupt  # as a SIGINT in the parent, while it follows the shares

    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        replay_split([log], run_config([log]), 2, progress=interrupt, min_messages=0)
    stopped = time.monotonic() - t0
    time.sleep(0.5)
    assert not mp.active_children()
    assert stopped < whole / 2, (stopped, whole)
