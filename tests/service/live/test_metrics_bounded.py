"""What a hostile client of the metrics endpoint can hold: a real service's endpoint, real sockets.

Before, every connection got a thread of its own and kept it for as long as the client liked
(idle connections, a request sent a byte at a time), and a request head of 6 MB was read whole.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from service_harness import running_bench

from service.live.httpserve import MAX_CONNECTIONS, BoundedServer

pytestmark = pytest.mark.integration


def _status(port: int) -> int:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
            reply.read()
            return int(reply.status)
    except urllib.error.HTTPError as err:
        return int(err.code)


def _idle(port: int, n: int) -> list[socket.socket]:
    """``n`` connections that send half a request line and nothing more."""
    socks = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.sendall(b"GET /metrics HT")
        socks.append(s)
    return socks


def test_idle_connections_hold_a_bounded_number_of_threads_for_a_bounded_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(BoundedServer, "deadline_s", 1.5)
    with running_bench(tmp_path, metrics_port=0, metrics_addr="127.0.0.1") as bench:
        port = bench.service.metrics.port
        assert port is not None and _status(port) == 200
        threads = threading.active_count()
        socks = _idle(port, 100)
        try:
            time.sleep(0.5)
            # one thread per connection served, at most MAX_CONNECTIONS (before: 100)
            assert threading.active_count() - threads <= MAX_CONNECTIONS
            # the connections past the bound are answered 503 at once, not left waiting
            answered, _, _ = select.select(socks[MAX_CONNECTIONS:], [], [], 1.0)
            assert answered
            assert {s.recv(100)[:12] for s in answered} == {b"HTTP/1.0 503"}
            # past the deadline the held connections are shut: a scrape is served again
            # while the client still keeps every socket open
            time.sleep(1.5)
            assert _status(port) == 200
            assert threading.active_count() - threads <= 2
        finally:
            for s in socks:
                s.close()


def test_a_huge_request_head_is_refused_after_64_kib(tmp_path: Path) -> None:
    with running_bench(tmp_path, metrics_port=0, metrics_addr="127.0.0.1") as bench:
        port = bench.service.metrics.port
        assert port is not None
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        line = b"X-" + b"a" * 65000 + b": b\r\n"

        def send() -> None:
            with contextlib.suppress(OSError):  # the server stops reading: the rest may not go
                s.sendall(b"GET /metrics HTTP/1.1\r\n" + line * 99)

        sender = threading.Thread(target=send, daemon=True)
        sender.start()
        try:
            # answered (before: the server read the 6 MB and waited for the head's end)
            assert s.recv(100).startswith(b"HTTP/1.0 431")
        finally:
            s.close()
            sender.join(5)
        assert _status(port) == 200
