"""Fixtures for service tests: a real service and real Zenoh client sessions on loopback."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from service_harness import WORLD, Bench, start_service

from service.live.sessions import client_config, free_port


@pytest.fixture
def bench(tmp_path: Path) -> Iterator[Bench]:
    port = free_port()
    service = start_service(tmp_path / "store", port)
    endpoint = f"tcp/127.0.0.1:{port}"
    client = zenoh.open(client_config(endpoint))
    try:
        yield Bench(service, client, endpoint, WORLD, tmp_path / "store")
    finally:
        client.close()
        service.close()
