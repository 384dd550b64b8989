"""The metrics endpoint's HTTP server: prometheus-client's WSGI app behind bounded connections.

prometheus-client's own ``start_http_server`` starts a thread per connection and waits on
each for ever: a client that opens connections and sends a request slowly (slowloris) or not
at all held a thread each, without end (300 idle connections: 300 threads), and one that sent
the longest request head ``http.server`` accepts (100 header lines of 64 KiB each) made the
server hold it, then parse it, on each connection at once (100 such connections took the
service process from 0.2 to 4.2 GB and stopped every robot's poses for over 20 s).

This server answers the same requests the same way (``/metrics``, OPTIONS, the ``name[]``
filter, gzip), and bounds what a client can hold:

* at most :data:`MAX_CONNECTIONS` connections are served at once; one more is answered
  ``503 Service Unavailable`` (``Retry-After: 1``) and closed, without a thread;
* a connection lives at most :data:`DEADLINE_S` seconds from its accept, request and answer
  included: past it, the server shuts its socket and its thread ends;
* a request head is read up to :data:`MAX_HEAD_BYTES` (a scrape's is a few hundred bytes):
  past it, the request is answered ``431 Request Header Fields Too Large`` and closed.
"""

from __future__ import annotations

import contextlib
import http.client
import io
import logging
import socket
import threading
import time
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, make_server

from prometheus_client import CollectorRegistry, make_wsgi_app
from prometheus_client.exposition import ThreadingWSGIServer

log = logging.getLogger(__name__)

#: Connections served at once; one more is refused with 503.
MAX_CONNECTIONS = 16
#: Seconds a connection may live from its accept (Prometheus' default scrape timeout is 10 s).
DEADLINE_S = 15.0
#: Refused connections waiting (half a second at most) to be closed; past them, closed at once.
CLOSING = 256
#: Bytes of request head (request line and headers) read from a connection.
MAX_HEAD_BYTES = 64 * 1024

BUSY = (
    b"HTTP/1.0 503 Service Unavailable\r\nRetry-After: 1\r\nContent-Length: 0\r\n"
    b"Connection: close\r\n\r\n"
)


class _HeadLimit(io.RawIOBase):
    """A reader of at most ``budget`` bytes of ``raw``: a line asked for past them raises."""

    def __init__(self, raw: Any, budget: int) -> None:
        super().__init__()
        self._raw, self._left = raw, budget

    def readable(self) -> bool:
        return True

    def close(self) -> None:
        """Close the connection's reader too (a reader left open keeps its socket open)."""
        self._raw.close()
        super().close()

    def readline(self, size: int | None = -1) -> bytes:
        want = self._left if size is None or size < 0 else min(size, self._left)
        if want <= 0:  # http.server answers 431 (Request Header Fields Too Large)
            raise http.client.LineTooLong(f"request head over {MAX_HEAD_BYTES} bytes")
        line: bytes = self._raw.readline(want)
        self._left -= len(line)
        return line

    def read(self, size: int | None = -1) -> bytes:
        want = self._left if size is None or size < 0 else min(size, self._left)
        if want <= 0:
            return b""
        data: bytes = self._raw.read(want)
        self._left -= len(data)
        return data


class _Handler(WSGIRequestHandler):
    """Logs nothing, and reads at most :data:`MAX_HEAD_BYTES` of a request."""

    def setup(self) -> None:
        super().setup()
        self.rfile = _HeadLimit(self.rfile, MAX_HEAD_BYTES)  # type: ignore[assignment]

    def log_message(self, format: str, *args: Any) -> None:
        """Nothing: a scrape is not worth a line."""


class BoundedServer(ThreadingWSGIServer):
    """A WSGI server of at most :data:`MAX_CONNECTIONS` connections of :data:`DEADLINE_S`."""

    max_connections = MAX_CONNECTIONS
    request_queue_size = 64  # the listen backlog (socketserver's is 5): refused, not unseen
    deadline_s = DEADLINE_S

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._open: dict[socket.socket, float] = {}  # connection -> its deadline (monotonic)
        self._open_lock = threading.Lock()
        self.refused = 0  # connections answered 503 (tests, figures)
        self.cut = 0  # connections shut at their deadline
        self._closing: list[socket.socket] = []  # refused, closed at the next service action
        super().__init__(*args, **kwargs)

    def process_request(self, request: Any, client_address: Any) -> None:
        with self._open_lock:
            full = len(self._open) >= self.max_connections
            if not full:
                self._open[request] = time.monotonic() + self.deadline_s
        if full:
            self._refuse(request)
            return
        super().process_request(request, client_address)

    def _refuse(self, request: socket.socket) -> None:
        """Answer 503 without a thread; the socket is closed at the next service action (what
        the client sent meanwhile read and dropped: a socket closed with unread input is reset,
        and the reset can overtake the 503)."""
        self.refused += 1
        with contextlib.suppress(OSError):
            request.setblocking(False)
            request.send(BUSY)
            request.shutdown(socket.SHUT_WR)
        if len(self._closing) >= CLOSING:
            _drain_and_close(request)
        else:
            self._closing.append(request)

    def shutdown_request(self, request: Any) -> None:
        with self._open_lock:
            self._open.pop(request, None)
        super().shutdown_request(request)

    def service_actions(self) -> None:
        """Shut the connections past their deadline (``serve_forever`` calls it twice a
        second): their thread's read or write fails at once and the thread ends."""
        closing, self._closing = self._closing, []
        for sock in closing:
            _drain_and_close(sock)
        now = time.monotonic()
        with self._open_lock:
            late = [s for s, deadline in self._open.items() if deadline <= now]
        for sock in late:
            self.cut += 1
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A connection that failed (cut, reset by its client): a debug line, no traceback."""
        log.debug("metrics connection from %s failed", client_address, exc_info=True)

    def open_connections(self) -> int:
        """Connections being served now."""
        with self._open_lock:
            return len(self._open)


def _drain_and_close(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        sock.recv(MAX_HEAD_BYTES)  # non-blocking: what has come
    sock.close()


def serve_metrics(
    port: int, addr: str, registry: CollectorRegistry
) -> tuple[BoundedServer, threading.Thread]:
    """Serve ``registry`` on ``http://addr:port/`` from a daemon thread, as prometheus-client's
    ``start_http_server`` does, with bounded connections.

    Raises:
        OSError: the address cannot be bound (port in use, address not local).
    """
    family, host = _family(addr, port)

    class _OfFamily(BoundedServer):
        address_family = family

    server = make_server(host, port, make_wsgi_app(registry), _OfFamily, handler_class=_Handler)
    thread = threading.Thread(target=server.serve_forever, name="rlutf-metrics", daemon=True)
    thread.start()
    return server, thread


def _family(addr: str, port: int) -> tuple[socket.AddressFamily, str]:
    """The address family and host to bind ``addr`` with (IPv6 addresses included)."""
    infos = socket.getaddrinfo(addr, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, _, _, _, sockaddr = infos[0]
    return family, str(sockaddr[0])
