"""Idle connections to the live view: bounded, and dropped at a handshake deadline.

The Foxglove SDK's server accepts every TCP connection and keeps it without end, handshake or
not: 19,000 idle connections held 19,000 of the service process's file descriptors (and 350
MB), and past the process's descriptor limit the service could no longer write its pose state
("Too many open files"), open a log file or accept a robot's link.
"""

from __future__ import annotations

import json
import os
import socket
import time

import pytest
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from service.keys import Keys
from service.live import wsgate
from service.live.foxview import FoxgloveView
from service.maps.book import MapBook

pytestmark = pytest.mark.integration

IDLE = 200


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _port(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


def test_idle_connections_cost_bounded_descriptors_and_are_dropped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(wsgate, "HANDSHAKE_S", 6.0)
    view = FoxgloveView(0, "127.0.0.1", MapBook(1 << 20), Keys("rlutf"))
    view.start()
    idle: list[socket.socket] = []
    try:
        assert view.url is not None
        port = _port(view.url)
        time.sleep(0.2)
        before, t0 = _fds(), time.monotonic()
        idle.extend(socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(IDLE))
        time.sleep(1.2)  # the refused ones are closed within a second
        # the test's own IDLE sockets, and at most one per client the view serves
        assert _fds() - before <= IDLE + wsgate.MAX_CLIENTS + 8
        # one more is told the view is busy rather than held
        extra = socket.create_connection(("127.0.0.1", port), timeout=5)
        extra.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        assert extra.recv(100).startswith(b"HTTP/1.1 503")
        extra.close()
        time.sleep(max(0.0, t0 + 7.0 - time.monotonic()))  # past the handshake deadline
        for sock in idle:  # closed: refused (503) or dropped at the deadline (nothing)
            sock.settimeout(2.0)
            got = b""
            while chunk := sock.recv(4096):
                got += chunk
            assert got == b"" or got.startswith(b"HTTP/1.1 503")
        # and a real client is served again
        url = view.url
        with connect(url, subprotocols=[Subprotocol("foxglove.sdk.v1")]) as ws:
            first = json.loads(ws.recv(timeout=5))
            assert first["op"] == "serverInfo"
    finally:
        for sock in idle:
            sock.close()
        view.close()
