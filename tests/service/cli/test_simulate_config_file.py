"""``rlutf simulate -c FILE`` goes where the file says, as the other tools.

Before, simulate set ``connect`` to tcp/127.0.0.1:7447 whenever -e was left out, so the
endpoints of a ``-c`` file were ignored (its help says "default: the -c file's"), and with the
deployment's file (``connect/timeout_ms: -1``) it waited for ever on that port, deaf to Ctrl-C.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from service.live.sessions import free_port


def test_simulate_connects_to_the_files_endpoint_and_asks_once(tmp_path: Path) -> None:
    port = free_port()
    path = tmp_path / "client.json5"
    path.write_text(
        f"{{mode: 'client', connect: {{endpoints: ['tcp/127.0.0.1:{port}'], timeout_ms: -1, "
        "exit_on_failure: false}, scouting: {multicast: {enabled: false}}}"
    )
    environ = {k: v for k, v in os.environ.items() if not k.upper().startswith("RLUTF_")}
    done = subprocess.run(
        [sys.executable, "-m", "service", "simulate", "-c", str(path), "--robots", "1"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
        cwd=tmp_path,
        env=environ,
    )
    assert done.returncode == 1, done.stderr
    assert f"cannot reach zenoh at tcp/127.0.0.1:{port} " in done.stderr
    assert "7447" not in done.stderr.split("(")[0]
