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


def _serve(tmp_path: Path, *flags: str) -> subprocess.Popen[str]:
    """``rlutf serve`` on a free port with its store in ``tmp_path``, no logs, no state."""
    argv = [sys.executable, "-m", "service", "serve", "-l", f"tcp/127.0.0.1:{free_port()}"]
    argv += ["--store", str(tmp_path / "store"), "--no-record", "--no-state", *flags]
    return subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)


def _said_until(proc: subprocess.Popen[str], *marks: str, timeout: float = 120.0) -> str:
    """What ``proc`` wrote on stderr until one of ``marks`` (or its end, or ``timeout``)."""
    assert proc.stderr is not None
    said = ""
    end = time.monotonic() + timeout
    while not any(m in said for m in marks) and time.monotonic() < end:
        line = proc.stderr.readline()
        if not line:
            break
        said += line
    return said


def test_serve_says_which_metrics_port_it_took(tmp_path: Path) -> None:
    proc = _serve(tmp_path, "--workers", "0", "--metrics-addr", "127.0.0.1", "--metrics-port", "0")
    try:
        said = _said_until(proc, "metrics on")
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


def test_serve_with_no_layout_flag_runs_one_process_per_usable_core(tmp_path: Path) -> None:
    """``rlutf serve`` as a first start types it: on two cores or more, one service process
    per core behind the router (the layout of processes); on one core, one process."""
    from service.cores import usable_cores

    cores = usable_cores()
    proc = _serve(tmp_path, "--instance", "auto")
    try:
        # the host's line, not its processes' (auto-pK)
        said = _said_until(proc, "ready: instance auto with", "ready: instance auto,", timeout=300)
        if cores >= 2:
            names = ", ".join(f"auto-p{k}" for k in range(cores))
            assert f"ready: instance auto with {cores} processes ({names})" in said, said
        else:
            assert "ready: instance auto, mode router" in said, said
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0


def test_a_host_says_one_metrics_endpoint_its_own(tmp_path: Path) -> None:
    """With several processes, each serves its metrics on a loopback port the host scrapes;
    only the host's endpoint, which merges them, is the operator's to scrape and is said."""
    proc = _serve(
        tmp_path, "--processes", "2", "--metrics-addr", "127.0.0.1", "--metrics-port", "0"
    )
    try:
        before = _said_until(proc, "ready:")
        assert "ready:" in before, before
        assert "metrics on" not in before, before  # a process's port, said before the host's
        after = _said_until(proc, "metrics on", timeout=30)
        found = re.search(r"metrics on http://127\.0\.0\.1:(\d+)/metrics", after)
        assert found, after
        with urllib.request.urlopen(f"http://127.0.0.1:{found[1]}/metrics", timeout=10) as reply:
            assert b"rlutf_host_processes_scraped" in reply.read()  # the host's, merged
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0


def test_a_host_in_client_mode_says_it_listens_on_nothing(tmp_path: Path) -> None:
    """A host of processes in ``--mode client`` binds no port of the robots' (its router is
    the one it connects to): its ready line said "listening on tcp/[::]:7447", where nothing
    listened, and an operator pointed robots there."""
    router = _serve(tmp_path / "a", "--workers", "0", "--instance", "a")
    port = None
    try:
        said = _said_until(router, "ready:", timeout=300)
        found = re.search(r"listening on tcp/127\.0\.0\.1:(\d+)", said)
        assert found, said
        port = found[1]
        argv = [*(sys.executable, "-m", "service", "serve", "--mode", "client"), "--no-store"]
        argv += ["-e", f"tcp/127.0.0.1:{port}", "--processes", "1", "--instance", "b"]
        argv += ["--no-record", "--no-state"]
        client = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
        try:
            line = _said_until(client, "ready:", timeout=300)
            assert "ready: instance b with 1 processes (b-p0)" in line, line
            assert f"listening on -, connecting to tcp/127.0.0.1:{port}" in line, line
            assert "7447" not in line, line
        finally:
            client.send_signal(signal.SIGINT)
            assert client.wait(timeout=60) == 0
    finally:
        router.send_signal(signal.SIGINT)
        assert router.wait(timeout=60) == 0
