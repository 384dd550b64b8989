"""A service waiting for its router stops on SIGTERM (``sessions.open_unless_stopped``).

Before, ``rlutf serve --mode client`` with the deployment's zenoh file (``connect/timeout_ms:
-1``: wait for the router) sat in ``zenoh.open`` while no router answered, where its signal
handlers never ran: SIGTERM and Ctrl-C did nothing (``docker compose stop`` and a pod deleted
while the router was down ended in SIGKILL after the grace period), and it said nothing of what it
waited for.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from service.live.sessions import StoppedWaiting, free_port, open_unless_stopped


def _waiting_file(tmp_path: Path) -> Path:
    path = tmp_path / "client.json5"
    port = free_port()
    path.write_text(
        f"{{mode: 'client', connect: {{endpoints: ['tcp/127.0.0.1:{port}'], timeout_ms: -1, "
        "exit_on_failure: false}, scouting: {multicast: {enabled: false}}, "
        "transport: {link: {tx: {queue: {size: {data: 16, data_high: 16}}}}}}"
    )
    return path


def test_open_gives_up_once_told_to_stop(tmp_path: Path) -> None:
    cfg = zenoh.Config.from_file(str(_waiting_file(tmp_path)))
    stop = threading.Event()
    threading.Timer(0.5, stop.set).start()
    start = time.monotonic()
    with pytest.raises(StoppedWaiting):
        open_unless_stopped(cfg, stop, ["tcp/127.0.0.1:1"])
    assert time.monotonic() - start < 3.0


def test_serve_waiting_for_its_router_stops_on_sigterm(tmp_path: Path) -> None:
    environ = {k: v for k, v in os.environ.items() if not k.upper().startswith("RLUTF_")}
    argv = [
        *("serve", "--mode", "client", "--config", str(_waiting_file(tmp_path))),
        *("--no-store", "--no-record", "--no-state", "--processes", "0", "--workers", "0"),
        *("--instance", "waiting"),
    ]
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", *argv],
        cwd=tmp_path,
        env={**environ, "PYTHONUNBUFFERED": "1"},
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        said = proc.stderr.readline()  # after 5 s: what it waits for
        assert "waiting for zenoh at tcp/127.0.0.1:" in said, said
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
