"""Zenoh's runtimes in a service process: accepting and receiving handed to the application's
runtime (``service.live.sessions.SERVICE_RUNTIME``) unless the operator's ``ZENOH_RUNTIME`` says
otherwise. Checked on a real router session in a process of its own, by its threads' names."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from service.config import Settings
from service.live.sessions import SERVICE_RUNTIME, free_port, service_config

ROOT = Path(__file__).resolve().parents[3]

# A router as the service opens it, a client linked to it (a link accepted), then the names of
# the process's threads (Zenoh names each runtime's threads: acc-0, rx-0, ...).
SCRIPT = """
import json, os, sys, time
import zenoh
from service.config import Settings
from service.live.sessions import client_config, service_config
endpoint = sys.argv[1]
router = zenoh.open(service_config(Settings(mode="router", listen=[endpoint])))
client = zenoh.open(client_config(endpoint))
client.put("rlutf/test/runtime", b"x")
time.sleep(0.5)
names = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
print(json.dumps({"names": names, "runtime": os.environ.get("ZENOH_RUNTIME")}), flush=True)
os._exit(0)
"""


def _threads(env: dict[str, str]) -> tuple[set[str], str | None]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, endpoint],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        cwd=ROOT,
        env={**env, "PYTHONPATH": str(ROOT)},
    )
    out = json.loads(done.stdout.strip().splitlines()[-1])
    return {n.rsplit("-", 1)[0] for n in out["names"] if "-" in n}, out["runtime"]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="thread names from /proc")
def test_a_service_process_accepts_and_receives_on_one_runtime() -> None:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    runtimes, runtime = _threads(env)
    assert runtime == SERVICE_RUNTIME
    assert "app" in runtimes and not {"rx", "acc"} & runtimes, runtimes


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="thread names from /proc")
def test_the_operators_zenoh_runtime_is_kept() -> None:
    env = {**os.environ, "ZENOH_RUNTIME": "(rx: (worker_threads: 1))"}
    runtimes, runtime = _threads(env)
    assert runtime == "(rx: (worker_threads: 1))"
    assert {"rx", "acc"} <= runtimes, runtimes


def test_the_default_is_set_only_where_the_environment_sets_none(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("ZENOH_RUNTIME", raising=False)
    service_config(Settings())
    assert os.environ["ZENOH_RUNTIME"] == SERVICE_RUNTIME
    monkeypatch.setenv("ZENOH_RUNTIME", "(app: (worker_threads: 2))")
    service_config(Settings())
    assert os.environ["ZENOH_RUNTIME"] == "(app: (worker_threads: 2))"
