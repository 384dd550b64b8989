"""What a default ``rlutf serve`` loads (issue 21): every module costs resident memory in every
process of the service, so what a default serve does not use stays out of it."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from service_harness import WORLD

from schemas import Map, encode
from service.live.sessions import client_config, free_port

pytestmark = pytest.mark.integration

#: Modules a serve without ``--foxglove-port``, ``--ros2`` or map import does not need: the
#: live view's SDK, plotting, image processing, scipy's linear algebra (numba loads it unless
#: told not to: ``rlutf.warmup``), a WebSocket client, and with no terminal, rich.
NOT_LOADED = ("foxglove", "matplotlib", "skimage", "PIL", "scipy.linalg", "websockets", "rich")

#: Runs ``rlutf serve`` as the console script does, and writes the modules it loaded, at exit.
SCRIPT = """
import atexit, json, sys
atexit.register(lambda: open(sys.argv[1], "w").write(json.dumps(sorted(sys.modules))))
from service.cli.main import main
sys.exit(main(sys.argv[2:]))
"""


def test_a_default_serve_loads_no_module_it_does_not_use(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "modules.json"
    argv = [sys.executable, "-c", SCRIPT, str(out), "serve", "-l", endpoint]
    argv += ["--store", str(tmp_path / "store"), "--record", str(tmp_path / "logs")]
    argv += ["--workers", "0"]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        said = ""
        end = time.monotonic() + 300  # the first start after an install compiles the kernels
        while "ready" not in said and time.monotonic() < end:
            line = proc.stderr.readline()
            if not line:
                break
            said += line
        assert "ready" in said, said
        with zenoh.open(client_config(endpoint)) as client:  # a map: stored, loaded, recorded
            client.put(
                "rlutf/maps/m1", encode(Map(map_id="m1", version=1, geometry=WORLD.to_geojson()))
            )
            time.sleep(2.0)
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    modules = set(json.loads(out.read_text()))
    assert "service.live.node" in modules and "rlutf._kernels" in modules  # it did serve
    assert (tmp_path / "store" / "m1.json").exists()
    unwanted = sorted(
        m for m in modules if any(m == n or m.startswith(n + ".") for n in NOT_LOADED)
    )
    assert not unwanted
