"""The live view forgets the robots the service evicts: their channels and newest messages.

Before, the view kept each robot it ever saw for the life of the process: its newest scan,
pose and initial pose (a scan of 8,192 beams is about 100 KB of JSON) and its three advertised
channels, which every client that connects is sent. A site whose robots come and go, or a
client that makes up robot ids, grew the process without bound and each new client's channel
list with it.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from service_harness import running_bench
from test_liveview import foxglove_client

from service.live.foxview import FoxgloveView

pytestmark = pytest.mark.integration


def test_evicted_robots_leave_the_live_view(tmp_path: Path) -> None:
    with running_bench(
        tmp_path, foxglove_port=0, robot_idle_s=1.0, handover_timeout_s=0.05
    ) as bench:
        view = bench.service.live
        assert isinstance(view, FoxgloveView) and view.url is not None
        robots = [bench.robot(f"gone{i}", i + 1) for i in range(12)]
        for _ in range(2):
            for r in robots:
                r.advance()
            time.sleep(0.05)
        end = time.monotonic() + 10
        while time.monotonic() < end and not all(bench.service.holds(r.robot_id) for r in robots):
            time.sleep(0.05)
        with foxglove_client(view.url) as watcher:
            watcher.pump(1.0)  # the channels are advertised at the next tick
            assert "/foxglove/robots/gone0/scan" in watcher.channels
            watcher.subscribe("/foxglove/fleet")
            end = time.monotonic() + 30
            while time.monotonic() < end and bench.service.robots_held() > 0:
                watcher.pump(0.1)
            assert bench.service.robots_held() == 0
            watcher.pump(0.5)
            # the watcher is told: the fleet's entities deleted
            deleted = {
                d["id"] for m in watcher.messages["/foxglove/fleet"] for d in m[1]["deletions"]
            }
            assert "robot/gone0" in deleted
        time.sleep(0.5)  # a tick of the view
        with foxglove_client(view.url) as client:
            client.pump(1.0)
            robot_channels = [t for t in client.channels if t.startswith("/foxglove/robots/")]
            assert robot_channels == []
            assert "/foxglove/tf" in client.channels
        assert not any("gone" in topic for topic in view._latest)
