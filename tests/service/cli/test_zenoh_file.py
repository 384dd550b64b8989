"""``-c/--config FILE`` of the commands that ask a running service: the file's endpoints are
the ones connected to, and a file made for the service (which retries for ever) costs a tool
one attempt, not a wait without end.

``rlutf health -c FILE`` connected to ``tcp/127.0.0.1:7447`` whatever FILE said (the default of
``-e`` replaced the file's endpoints): with deploy/compose.secure.yaml's
``RLUTF_HEALTH_ARGS: --config /etc/rlutf/zenoh-secure.json5`` (``connect.timeout_ms: -1``) the
health check waited for ever on a port nothing listens on, so no container was ever healthy;
``rlutf robots -c secure.json5`` said "cannot reach zenoh at tcp/127.0.0.1:7447".
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from service.cli.main import main
from service.live.sessions import free_port

DEPLOY = Path(__file__).resolve().parents[3] / "deploy" / "zenoh"


@pytest.fixture
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", f'["{endpoint}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config):
        yield endpoint


def _service_file(tmp_path: Path, endpoint: str, retry: bool = True) -> Path:
    """deploy/zenoh/service-client.json5 (``timeout_ms: -1``: retry for ever), pointed at
    ``endpoint``; without ``retry``, zenoh's default for a client (one attempt)."""
    text = (DEPLOY / "service-client.json5").read_text()
    assert "tcp/zenoh-router:7447" in text and "timeout_ms: -1," in text
    if not retry:
        text = text.replace("timeout_ms: -1,", "")
    path = tmp_path / "client.json5"
    path.write_text(text.replace("tcp/zenoh-router:7447", endpoint))
    return path


def test_a_tool_connects_to_the_endpoints_of_its_config_file(
    router: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _service_file(tmp_path, router, retry=False)
    code = main(["health", "-c", str(path), "--timeout", "0.5"])
    err = capsys.readouterr().err
    assert code == 1 and "no instance answered" in err, err  # the router answered, no service
    assert "access control, may the identity of the -c file query it?" in err, err
    code = main(["robots", "-c", str(path), "-e", "tcp/127.0.0.1:1", "--timeout", "0.5"])
    assert code == 1 and "cannot reach zenoh at tcp/127.0.0.1:1" in capsys.readouterr().err


def test_a_config_file_that_retries_for_ever_costs_a_tool_one_attempt(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    path = _service_file(tmp_path, endpoint)
    started = time.monotonic()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "service", "health", "-c", str(path), "--timeout", "1"],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    except subprocess.TimeoutExpired:
        pytest.fail("rlutf health -c FILE waited for the router for ever")
    assert time.monotonic() - started < 20
    assert done.returncode == 1 and f"cannot reach zenoh at {endpoint}" in done.stderr, done.stderr


def _config(argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict[str, object]:
    import json

    assert main(["config", *argv]) == 0
    return dict(json.loads(capsys.readouterr().out))


def test_serve_takes_what_its_zenoh_file_states_where_no_flag_says(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``rlutf serve -c FILE`` ran mode router on ``tcp/[::]:7447`` whatever FILE said: the
    settings' defaults replaced its ``mode`` and ``listen``, so deploy/zenoh's TLS client file
    without ``--mode client`` opened an unencrypted router port on every interface."""
    secure = str(DEPLOY / "service-client-secure.json5")
    got = _config(["-c", secure], capsys)
    assert (got["mode"], got["connect"]) == ("client", ["tls/zenoh-router:7447"])
    path = tmp_path / "router.json5"
    path.write_text('{ mode: "peer", listen: { endpoints: ["tcp/127.0.0.1:7999"] },\n'
                    "  scouting: { multicast: { enabled: true } } }")  # fmt: skip
    got = _config(["-c", str(path)], capsys)
    assert (got["mode"], got["listen"], got["multicast_scouting"]) == (
        "peer", ["tcp/127.0.0.1:7999"], True
    )  # fmt: skip
    # what is given otherwise wins, as before: flags, then RLUTF_* (a flag here)
    got = _config(["-c", str(path), "--mode", "router", "-l", "tcp/127.0.0.1:1"], capsys)
    assert (got["mode"], got["listen"]) == ("router", ["tcp/127.0.0.1:1"])
    # a file that states none of them changes nothing
    (tmp_path / "plain.json5").write_text("{ transport: {} }")
    got = _config(["-c", str(tmp_path / "plain.json5")], capsys)
    assert (got["mode"], got["listen"], got["connect"]) == ("router", ["tcp/[::]:7447"], [])


def test_serve_listens_where_its_zenoh_file_says(tmp_path: Path) -> None:
    port = free_port()
    path = tmp_path / "z.json5"
    path.write_text(f'{{ mode: "router", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }} }}')
    argv = ["serve", "-c", str(path), "--no-store", "--no-record", "--workers", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", *argv, "--processes", "0"],
        cwd=tmp_path,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        while line and "ready" not in line:
            line = proc.stderr.readline()
        assert f"listening on tcp/127.0.0.1:{port}" in line, line
    finally:
        proc.terminate()
        proc.wait(30)
