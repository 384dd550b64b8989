"""A recording service killed with SIGKILL leaves a ``.part`` file that recovers and replays."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from mcaplog_fixtures import simulated_inputs

from service.cli.main import main
from service.live.sessions import client_config, free_port
from service.logs.mcapread import LogFile

pytestmark = pytest.mark.integration


def _open_client(endpoint: str, proc: subprocess.Popen[bytes], timeout: float) -> zenoh.Session:
    end = time.monotonic() + timeout
    while True:
        try:
            return zenoh.open(client_config(endpoint))
        except zenoh.ZError:
            if time.monotonic() > end or proc.poll() is not None:
                raise
            time.sleep(0.1)


def test_sigkilled_service_log_recovers_and_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    logs = tmp_path / "logs"
    env = {**os.environ, "RLUTF_EVENT_INTERVAL_S": "0"}
    env.pop("RLUTF_SETTINGS", None)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service",
            "serve",
            "--listen",
            endpoint,
            "--store",
            str(tmp_path / "store"),
            "--record",
            str(logs),
            "--workers",
            "0",
            "--instance",
            "crash",
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        client = _open_client(endpoint, proc, 20.0)
        try:
            end = time.monotonic() + 10
            while not list(client.liveliness().get("rlutf/service/crash", timeout=1.0)):
                assert time.monotonic() < end, "the service did not come up"
            records = simulated_inputs(("r1", "r2"), steps=30, seed=8)
            client.put(records[0].topic, records[0].payload)  # the map
            time.sleep(0.5)
            for r in records[1:]:
                client.put(r.topic, r.payload)
                if r.schema_name == "rlutf.LaserScan":
                    time.sleep(0.03)
            time.sleep(1.5)  # at least one flush after the last inputs
        finally:
            client.close()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if proc.stderr is not None:
            proc.stderr.close()
    parts = list(logs.glob("*.mcap.part"))
    assert len(parts) == 1 and not list(logs.glob("*.mcap"))
    part = parts[0]
    assert main(["log", "info", str(part)]) == 2
    assert "rlutf log recover" in capsys.readouterr().err
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(part), str(fixed)]) == 0
    capsys.readouterr()
    with LogFile(fixed) as lf:
        assert lf.config() is not None and lf.config()["instance"] == "crash"  # type: ignore[index]
        assert lf.count({"rlutf.LaserScan"}) >= 50
        assert lf.count({"rlutf.PoseEstimate"}) >= 40
    code = main(["replay", str(fixed), "--out", str(tmp_path / "replayed.mcap"), "--quiet"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "audit: passed" in out
