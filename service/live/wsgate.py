"""The live view's door: at most :data:`MAX_CLIENTS` connections, each with a handshake deadline.

The Foxglove SDK's server accepts every TCP connection and keeps it for as long as the client
likes, handshake or not: 19,000 idle connections to the live view's port held 19,000 of the
service process's file descriptors and 350 MB, without end, and past its descriptor limit (often
1,024) the service could no longer write its pose state (``EMFILE``), open its next log file or
accept a robot's Zenoh link. The SDK has no setting that bounds them.

So the SDK listens on a loopback port of its own, and this door listens where the operator
asked: it serves at most :data:`MAX_CLIENTS` clients at once (one more is answered ``503
Service Unavailable`` and closed, at most one log line per :data:`LOG_EVERY_S`), gives a client
:data:`HANDSHAKE_S` seconds to send its HTTP upgrade request (a head of at most
:data:`MAX_HEAD_BYTES`; past either it is closed), then relays the bytes both ways, two threads a
client. A client that never reads stalls only its own relay: the SDK sees it as slow and keeps
only its newest 1,024 messages for it (it disconnects it once its control messages fill too).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time

log = logging.getLogger(__name__)

#: Clients served at once; one more is refused with 503.
MAX_CLIENTS = 32
#: Seconds a client has, from its accept, to send its upgrade request whole.
HANDSHAKE_S = 10.0
#: Bytes of upgrade request read (a browser's is under 2 KiB).
MAX_HEAD_BYTES = 16 * 1024
#: Refused sockets waiting (half a second) to be closed; past them, closed at once.
CLOSING = 256
#: Seconds between two log lines about refused clients.
LOG_EVERY_S = 10.0

BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 5\r\nContent-Length: 0\r\n"
    b"Connection: close\r\n\r\n"
)


class Gate:
    """Listens on ``(addr, port)`` and relays each admitted client to ``127.0.0.1:target``.

    Raises:
        OSError: ``addr:port`` cannot be bound (in use, not a local address).
    """

    def __init__(self, addr: str, port: int, target: int) -> None:
        infos = socket.getaddrinfo(addr, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, _, _, _, sockaddr = infos[0]
        self._listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(sockaddr)
            self._listener.listen(64)
        except OSError:
            self._listener.close()
            raise
        self.port: int = self._listener.getsockname()[1]
        self.target = target
        self._lock = threading.Lock()
        self._clients: set[socket.socket] = set()
        self._closed = False
        self.refused = 0  # clients answered 503 (tests, figures)
        self.timed_out = 0  # clients closed without a whole upgrade request in time
        self._said_at = 0.0
        self._closing: list[tuple[float, socket.socket]] = []  # refused: (when, socket)
        self._said = 0
        threading.Thread(target=self._accept, name="rlutf-foxglove-gate", daemon=True).start()

    def clients(self) -> int:
        """Clients being served now."""
        with self._lock:
            return len(self._clients)

    def close(self) -> None:
        """Stop listening and close every client."""
        with self._lock:
            self._closed = True
            clients = list(self._clients)
        with contextlib.suppress(OSError):
            self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        for conn in clients:
            _shut(conn)

    def _accept(self) -> None:
        self._listener.settimeout(0.25)  # to close the refused sockets in time
        while True:
            self._close_refused(time.monotonic() - 0.5)
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                if self._closed:
                    return
                time.sleep(0.05)  # EMFILE and the like: the next accept may succeed
                continue
            conn.settimeout(None)
            with self._lock:
                full = len(self._clients) >= MAX_CLIENTS
                if not full:
                    self._clients.add(conn)
            if full:
                self._refuse(conn)
            else:
                threading.Thread(
                    target=self._serve, args=(conn,), name="rlutf-foxglove-client", daemon=True
                ).start()

    def _refuse(self, conn: socket.socket) -> None:
        self.refused += 1
        self._said += 1
        with contextlib.suppress(OSError):
            conn.setblocking(False)
            conn.send(BUSY)
            conn.shutdown(socket.SHUT_WR)
        # Closed half a second later, what the client sent meanwhile read and dropped: a socket
        # closed with unread input is reset, and the reset can overtake the 503.
        self._closing.append((time.monotonic(), conn))
        if len(self._closing) > CLOSING:
            self._close_refused(time.monotonic())
        now = time.monotonic()
        if now - self._said_at >= LOG_EVERY_S:
            log.warning(
                "live view: %d connection(s) refused: %d clients already connected "
                "(service.live.wsgate.MAX_CLIENTS)",
                self._said,
                MAX_CLIENTS,
            )
            self._said_at, self._said = now, 0

    def _close_refused(self, before: float) -> None:
        while self._closing and self._closing[0][0] <= before:
            _, conn = self._closing.pop(0)
            with contextlib.suppress(OSError):
                conn.recv(MAX_HEAD_BYTES)  # non-blocking: what has come
            conn.close()

    def _serve(self, conn: socket.socket) -> None:
        upstream: socket.socket | None = None
        try:
            head = _read_head(conn)
            if head is None:
                self.timed_out += 1
                return
            upstream = socket.create_connection(("127.0.0.1", self.target), timeout=5.0)
            upstream.settimeout(None)
            conn.settimeout(None)
            upstream.sendall(head)
            back = threading.Thread(
                target=_relay, args=(upstream, conn), name="rlutf-foxglove-relay", daemon=True
            )
            back.start()
            _relay(conn, upstream)
            back.join()
        except OSError:
            pass
        finally:
            with self._lock:
                self._clients.discard(conn)
            _shut(conn)
            if upstream is not None:
                _shut(upstream)


def _read_head(conn: socket.socket) -> bytes | None:
    """What the client sent up to the end of its upgrade request's head (and any bytes after
    it), or ``None`` if it did not within :data:`HANDSHAKE_S` and :data:`MAX_HEAD_BYTES`."""
    deadline = time.monotonic() + HANDSHAKE_S
    data = b""
    while b"\r\n\r\n" not in data:
        left = deadline - time.monotonic()
        if left <= 0 or len(data) >= MAX_HEAD_BYTES:
            return None
        conn.settimeout(left)
        try:
            chunk = conn.recv(MAX_HEAD_BYTES - len(data))
        except TimeoutError:
            return None
        if not chunk:
            return None
        data += chunk
    return data


def _relay(src: socket.socket, dst: socket.socket) -> None:
    """Copy ``src`` to ``dst`` until either ends; then end both."""
    try:
        while chunk := src.recv(65536):
            dst.sendall(chunk)
    except OSError:
        pass
    finally:
        _shut(src)
        _shut(dst)


def _shut(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        sock.close()
