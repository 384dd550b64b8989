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

from service.live.sessions import (
    OPEN_END_WAIT_S,
    StoppedWaiting,
    free_port,
    open_unless_stopped,
)


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
    # told at 0.5 s; the open, which waits for a router that never answers, is given up on
    assert time.monotonic() - start < 0.5 + OPEN_END_WAIT_S + 1.5


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


_STOPPED_WHILE_OPENING = """
import json, sys, threading
import zenoh
import service.cli.main, service.live.node  # a service's modules: an end of the interpreter as long
from service.live.sessions import StoppedWaiting, free_port, open_unless_stopped
cfg = zenoh.Config()
cfg.insert_json5("mode", '"router"')
cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port()}"]))
cfg.insert_json5("scouting/multicast/enabled", "false")
stop = threading.Event()
threading.Timer(float(sys.argv[1]), stop.set).start()
try:
    open_unless_stopped(cfg, stop, [])
    print("opened")
except StoppedWaiting:
    print("stopped")
"""


def test_a_stop_while_zenoh_opens_ends_the_process_cleanly() -> None:
    """A stop while ``zenoh.open`` runs: the process ends with exit 0. It aborted (exit -6,
    "FATAL: exception not rethrown") when the opening thread came back from zenoh while the
    interpreter ended (``rlutf serve`` signalled a second or two into its start). Stops at
    several moments of the open, each its own process, all at once."""
    delays = [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7]
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _STOPPED_WHILE_OPENING, str(delay)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for delay in delays
    ]
    for delay, proc in zip(delays, procs, strict=True):
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, f"stop at {delay} s: exit {proc.returncode}\n{out}{err}"
        assert "FATAL" not in err and "Traceback" not in err, err
        assert out.strip() in ("stopped", "opened"), out
