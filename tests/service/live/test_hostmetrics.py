"""The host's metrics endpoint reads its processes' at once: processes that hang cost a scrape
one timeout, not one each."""

from __future__ import annotations

import socket
import time
import urllib.request
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import pytest
from prometheus_client import CollectorRegistry, Counter

from service.live import hostmetrics
from service.live.hostmetrics import HostMetrics
from service.live.httpserve import serve_metrics


@contextmanager
def _silent_port() -> Iterator[int]:
    """A loopback port whose connections are taken by the kernel and never answered (a
    process that hung)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(8)
        yield int(s.getsockname()[1])


@contextmanager
def _process_metrics(name: str) -> Iterator[int]:
    """A process's own metrics endpoint, with one series labelled ``instance=name``."""
    registry = CollectorRegistry()
    counter = Counter("rlutf_test_total", "A test counter.", ["instance"], registry=registry)
    counter.labels(instance=name).inc(3)
    server, _ = serve_metrics(0, "127.0.0.1", registry)
    try:
        yield int(server.server_address[1])
    finally:
        server.shutdown()
        server.server_close()


def test_a_scrape_waits_for_hung_processes_once_not_once_each(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(hostmetrics, "SCRAPE_TIMEOUT_S", 1.0)
    with ExitStack() as stack:
        ports = [stack.enter_context(_process_metrics("p0"))]
        ports += [stack.enter_context(_silent_port()) for _ in range(3)]
        ports.append(stack.enter_context(_process_metrics("p4")))
        host = HostMetrics(ports, 0, "127.0.0.1")
        host.start()
        stack.callback(host.close)
        t0 = time.monotonic()
        url = f"http://127.0.0.1:{host.port}/metrics"
        text = urllib.request.urlopen(url, timeout=30).read().decode()
        took = time.monotonic() - t0
    # in turn, three hung processes took 3 s; at once, one timeout
    assert took < 2.5, took
    assert "rlutf_host_processes_scraped 2.0" in text
    assert 'rlutf_test_total{instance="p0"} 3.0' in text
    assert 'rlutf_test_total{instance="p4"} 3.0' in text
    assert text.index('instance="p0"') < text.index('instance="p4"')  # the processes' order
