"""A process of its own for work that must not stall or endanger the service: there only while
it is used.

Validating a map is such work (:class:`service.maps.book.MapChecker`): decoding one holds the
interpreter's lock for seconds (the JSON parser and pydantic are C code that lets no other
thread run), and a map is untrusted input: the largest accepted payload (``max_map_bytes``,
64 MB) takes a gigabyte and tens of seconds to decode. In a process of its own the service's
threads run on meanwhile; a call that takes longer than ``timeout_s`` has its process killed
and fails; a process that dies (the kernel's out-of-memory killer picks the process that grew)
fails the one call, and the next call starts a new process.

The process costs resident memory for as long as it runs (its interpreter and imports, about
60 MB), which maps, put a few times a day, do not need: it is started by :meth:`HelperProcess.
start` or the first call and ends when ``idle_s`` passed without a call.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import multiprocessing as mp
import signal
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

log = logging.getLogger(__name__)

#: How long a helper process lives without a call, seconds: a map checker is about 57 MB
#: resident, one per service process of the default layout, so it goes soon after its maps
#: (kept a minute from the service's start, two of them held the service at 200 robots at 517
#: to 522 MB resident instead of 464: BENCHMARKS.md, "200 robots on 0.5.1").
IDLE_S = 10.0
#: The longest call, seconds (a 64 MB map decodes in about 15 s on one free core).
TIMEOUT_S = 120.0
#: The longest start of a process (its imports), seconds.
START_S = 60.0


class HelperFailed(RuntimeError):
    """A call that did not return: its process took longer than the timeout (and was killed),
    died, or raised."""


def malloc_trim() -> Callable[[], None] | None:
    """glibc's ``malloc_trim(0)``, which gives the heap's free pages back to the system, or
    ``None`` where the C library has none (musl, macOS)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return lambda: trim(0)


def _serve(conn: Connection, handle: Callable[..., Any]) -> None:
    """The helper process: answer each call with ``("ok", result)`` or ``("raised", text)``
    until the pipe closes."""
    # Ctrl-C and a hang-up are the service's (a terminal signals the whole process group): it
    # closes the pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    trim = malloc_trim()
    conn.send(("ready",))
    while True:
        try:
            args = conn.recv()
        except (EOFError, OSError):
            return
        try:
            reply: tuple[str, Any] = ("ok", handle(*args))
        except Exception as err:  # a bug in handle: the caller gets its text
            reply = ("raised", f"{type(err).__name__}: {err}")
        conn.send(reply)
        # What the call took (a map of real size decoded: 100 MB and more) goes back to the
        # system now, not when the process ends idle: collected, and the heap trimmed.
        del args, reply
        gc.collect()
        if trim is not None:
            trim()


class HelperProcess:
    """Runs ``handle(*args)`` in a spawned process, one call at a time.

    Args:
        handle: a module-level function (the process imports it by name) whose arguments and
            result can be pickled; expected failures belong in its result, not in exceptions.
        name: the process's name (``ps``, logs).
        idle_s: the process ends when this long passed without a call.
        timeout_s: a call taking longer has its process killed and raises
            :class:`HelperFailed`.
    """

    def __init__(
        self,
        handle: Callable[..., Any],
        name: str,
        idle_s: float = IDLE_S,
        timeout_s: float = TIMEOUT_S,
    ) -> None:
        self.handle = handle
        self.name = name
        self.idle_s = idle_s
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._conn: Connection | None = None
        self._process: BaseProcess | None = None
        self._last = 0.0
        self._timer: threading.Timer | None = None
        self.started = 0
        """Processes started so far."""

    @property
    def pid(self) -> int | None:
        """The running process's id, ``None`` when none runs."""
        p = self._process
        return p.pid if p is not None and p.is_alive() else None

    def start(self) -> None:
        """Start the process now, if none runs, and wait until it can take a call (its imports
        take a second or more: at the service's start, not when the first map comes)."""
        with self._lock:
            self._ensure()
            self._idle_from_now()

    def call(self, *args: Any) -> Any:
        """``handle(*args)`` in the process; calls from several threads take turns.

        Raises:
            HelperFailed: the call took longer than ``timeout_s``, its process died, or
                ``handle`` raised.
        """
        with self._lock:
            conn = self._ensure()
            try:
                conn.send(args)
                if not conn.poll(self.timeout_s):
                    self._stop(kill=True)
                    raise HelperFailed(f"took longer than {self.timeout_s:g} s (stopped)")
                reply = conn.recv()
            except (EOFError, OSError) as err:  # died: killed out of memory, or by hand
                code = self._process.exitcode if self._process is not None else None
                self._stop(kill=True)
                raise HelperFailed(f"its process died (exit code {code})") from err
            finally:
                self._idle_from_now()
        if reply[0] == "raised":
            raise HelperFailed(f"it raised {reply[1]}")
        return reply[1]

    def close(self) -> None:
        """End the process, if any."""
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
            self._stop(kill=False)

    def _ensure(self) -> Connection:
        if self._conn is not None and self._process is not None and self._process.is_alive():
            return self._conn
        self._stop(kill=True)
        ctx = mp.get_context("spawn")
        mine, theirs = ctx.Pipe()
        process = ctx.Process(
            target=_serve, args=(theirs, self.handle), name=self.name, daemon=True
        )
        process.start()
        theirs.close()
        self._conn, self._process = mine, process
        self.started += 1
        try:
            if not mine.poll(START_S):
                raise HelperFailed(f"did not start within {START_S:g} s")
            mine.recv()  # ("ready",)
        except (EOFError, OSError, HelperFailed) as err:
            self._stop(kill=True)
            raise HelperFailed(f"its process could not start: {err}") from err
        log.debug("%s: process %d started", self.name, process.pid)
        return mine

    def _stop(self, kill: bool) -> None:
        conn, process = self._conn, self._process
        self._conn = self._process = None
        if conn is not None:
            conn.close()  # the process reads the end of the pipe and returns
        if process is not None:
            if kill:
                process.kill()
            process.join(5.0)
            if process.is_alive():
                process.kill()
                process.join()
            log.debug("%s: process %d ended", self.name, process.pid)

    def _idle_from_now(self) -> None:
        self._last = time.monotonic()
        if self._timer is not None:
            self._timer.cancel()
        self._timer = threading.Timer(self.idle_s, self._end_if_idle)
        self._timer.daemon = True
        self._timer.start()

    def _end_if_idle(self) -> None:
        # A call may have come just before the timer fired: its own timer ends the process.
        with self._lock:
            if time.monotonic() - self._last >= self.idle_s * 0.99:
                self._stop(kill=False)
