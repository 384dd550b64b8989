"""``rlutf serve`` as an operator starts it: the metrics port it took is said."""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from service.live.sessions import free_port

pytestmark = pytest.mark.integration


def test_serve_says_which_metrics_port_it_took(tmp_path: Path) -> None:
    argv = [
        *(sys.executable, "-m", "service", "serve"),
        *("-l", f"tcp/127.0.0.1:{free_port()}", "--store", str(tmp_path / "store")),
        *("--no-record", "--no-state", "--workers", "0"),
        *("--metrics-addr", "127.0.0.1", "--metrics-port", "0"),
    ]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        said = ""
        end = time.monotonic() + 120
        while "metrics on" not in said and time.monotonic() < end:
            line = proc.stderr.readline()
            if not line:
                break
            said += line
        found = re.search(r"metrics on http://127\.0\.0\.1:(\d+)/metrics", said)
        assert found, said
        port = int(found[1])
        assert port > 0
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as reply:
            assert b"rlutf_messages_received_total" in reply.read()
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0


def test_serve_names_a_live_view_port_in_use(tmp_path: Path) -> None:
    """The live view's errors are caught without importing Foxglove's SDK up front."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = [
            *(sys.executable, "-m", "service", "serve"),
            *("-l", f"tcp/127.0.0.1:{free_port()}", "--store", str(tmp_path / "store")),
            *("--no-record", "--no-state", "--workers", "0", "--foxglove-port", str(port)),
        ]
        done = subprocess.run(argv, check=False, capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stderr
    assert "choose another --foxglove-port" in done.stderr
    assert str(port) in done.stderr
