"""The Kubernetes readiness probe reaches the router as the service does: through the zenoh file
mounted at /etc/rlutf, so that the secured setup of deploy/README.md (the ConfigMap swapped for
``service-client-secure.json5``, a TLS-only router) keeps pods Ready.

The probe was ``rlutf health --connect tcp/zenoh-router:7447``: plain TCP to a router that
listens on TLS only, so with the secured configuration no rlutf pod ever became Ready (and
``RLUTF_HEALTH_ARGS`` said the same for the image's HEALTHCHECK)."""

from __future__ import annotations

import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from service.cli.main import main
from service.live.sessions import free_port

K8S = Path(__file__).resolve().parents[2] / "deploy" / "k8s"


def _container() -> dict[str, Any]:
    doc = yaml.safe_load((K8S / "rlutf-deployment.yaml").read_text())
    (container,) = doc["spec"]["template"]["spec"]["containers"]
    return dict(container)


def _flag(argv: list[str], flag: str) -> str | None:
    return argv[argv.index(flag) + 1] if flag in argv else None


def test_the_probe_and_health_args_use_the_services_zenoh_file() -> None:
    container = _container()
    config = _flag(container["args"], "--config")
    assert config == "/etc/rlutf/zenoh.json5"
    probe = container["readinessProbe"]["exec"]["command"]
    env = {e["name"]: e.get("value") for e in container["env"]}
    for argv in (probe[2:], shlex.split(env["RLUTF_HEALTH_ARGS"])):
        assert _flag(argv, "--config") == config, argv
        assert "--connect" not in argv and "-e" not in argv, argv  # it would bypass the file


@pytest.fixture
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", f'["{endpoint}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config):
        yield endpoint


def test_the_probe_reaches_the_router_of_the_configmaps_file(
    router: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (doc,) = [
        d
        for d in yaml.safe_load_all((K8S / "rlutf-configmap.yaml").read_text())
        if d["metadata"]["name"] == "rlutf-zenoh-config"
    ]
    text = doc["data"]["zenoh.json5"]
    assert "tcp/zenoh-router:7447" in text
    path = tmp_path / "zenoh.json5"
    path.write_text(text.replace("tcp/zenoh-router:7447", router))
    probe = _container()["readinessProbe"]["exec"]["command"]
    assert probe[:2] == ["rlutf", "health"]
    argv = [str(path) if a == "/etc/rlutf/zenoh.json5" else a for a in probe[1:]]
    argv[argv.index("--timeout") + 1] = "0.5"
    assert main(argv) == 1  # the router answered; no service runs behind it
    assert "no instance answered" in capsys.readouterr().err
