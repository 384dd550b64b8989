"""Zenoh session configurations: the service's, a client's, and a free loopback port.

One home for the keys every configuration sets (``mode``, ``listen/endpoints``,
``connect/endpoints``, ``scouting/multicast/enabled``), so the service, the demo, the tests and
the benchmarks open sessions the same way.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Final

import zenoh

from service.config import Settings

log = logging.getLogger(__name__)

#: Batches (64 kB each) a link's send queue holds per data priority (zenoh's maximum; its default
#: is 2).
TX_QUEUE_BATCHES = 16
#: Their priorities: robots' inputs (``data``) and the service's poses (``data_high``).
TX_QUEUE_PRIORITIES = ("data", "data_high")
#: Zenoh's runtimes in a service process (its ``ZENOH_RUNTIME`` environment variable, unless set):
#: the runtimes that accept links and receive on them handed over to the application's, with two
#: threads, as in Zenoh's own example of the variable (``zenoh_runtime::ZRuntime``). A link's
#: socket is watched by the runtime that opened or accepted it (the acceptor's in a router, the
#: application's in a client), and by default each batch that arrives wakes that runtime's
#: thread and then a receiving one: at 200 robots, 2,000 wake-ups a second of the host's
#: acceptor thread (0.013 ms of CPU a scan) and as many of the other process's application
#: thread. With one runtime for all three, one thread wakes (BENCHMARKS.md, "Zenoh's runtimes in
#: a service process").
SERVICE_RUNTIME = "(rx: (handover: app), acc: (handover: app), app: (worker_threads: 2))"


def session_config(
    mode: str,
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    file: Path | None = None,
) -> zenoh.Config:
    """A zenoh configuration: ``file`` if given, then these settings on top.

    Without a file, each link's send queue holds :data:`TX_QUEUE_BATCHES` batches of data (zenoh's
    default: 2), and zenoh's shared-memory transport is off. A router drops a robot's sample
    (sent with congestion control ``drop``, as robots send scans) when the link to a subscriber
    has been full for a millisecond; with 2 batches of 64 kB, a service process descheduled for
    about 10 ms on a busy host lost a burst of scans that no part of the service ever saw
    (BENCHMARKS.md, "Scans lost on the host's own links"). Queues are allocated as they fill.
    With shared memory on, every session on this host that puts a message over 3 kB makes a 16 MB
    shared pool that each session it reaches maps, which is resident memory in both (20
    simulated robots on one host took a router from 67 to 394 MB); over the network it does
    nothing. With a file, the file decides both (zenoh's defaults: 2 batches, shared memory on).

    Args:
        mode: ``router``, ``peer`` or ``client``.
        listen: endpoints to listen on; ignored in client mode, left as configured when empty.
        connect: endpoints to connect to; left as configured when empty.
        multicast_scouting: whether to find peers by multicast.
        file: a zenoh JSON5 configuration file to start from.
    """
    cfg = zenoh.Config.from_file(str(file)) if file else (zenoh.Config())
    if file is None:
        cfg.insert_json5("transport/shared_memory/enabled", "false")
        for priority in TX_QUEUE_PRIORITIES:
            cfg.insert_json5(f"transport/link/tx/queue/size/{priority}", str(TX_QUEUE_BATCHES))
    cfg.insert_json5("mode", json.dumps(mode))
    if listen and mode != "client":
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    return cfg


def zenoh_config(settings: Settings) -> zenoh.Config:
    """A zenoh configuration from the settings (file first, then the flags on top)."""
    return session_config(
        settings.mode,
        listen=settings.listen,
        connect=settings.connect,
        multicast_scouting=settings.multicast_scouting,
        file=settings.zenoh_config,
    )


#: What a zenoh file may state that a setting also sets: the setting, the file's key.
FILE_KEYS = (
    ("mode", "mode"),
    ("listen", "listen/endpoints"),
    ("connect", "connect/endpoints"),
    ("multicast_scouting", "scouting/multicast/enabled"),
)


def with_file(settings: Settings) -> Settings:
    """``settings`` with what its zenoh file (``-c/--config``) states of :data:`FILE_KEYS`
    where the setting is not given (a flag, an ``RLUTF_*`` variable, the settings file).

    Before, the settings' defaults replaced the file's values: a file saying ``mode: "client"``
    and ``connect`` to a TLS router ran a router that listened on ``tcp/[::]:7447``, every
    interface, unencrypted; a file's ``listen`` endpoints were not listened on.

    Raises:
        zenoh.ZError: the file is not one zenoh reads (:func:`zenoh_config` on it says why).
    """
    if settings.zenoh_config is None:
        return settings
    cfg = zenoh.Config.from_file(str(settings.zenoh_config))
    default = zenoh.Config()
    stated: dict[str, object] = {}
    for name, key in FILE_KEYS:
        value = json.loads(cfg.get_json(key))
        if name in settings.model_fields_set or value in (None, []):
            continue
        if isinstance(value, dict):  # per mode, as zenoh's own default: stated if not that
            if value == json.loads(default.get_json(key)):
                continue
            value = value.get(str(stated.get("mode", settings.mode)))
            if not isinstance(value, list) or not value:
                continue
        stated[name] = [str(v) for v in value] if isinstance(value, list) else value
    return settings.model_copy(update=stated) if stated else settings


def service_config(settings: Settings) -> zenoh.Config:
    """The service's own zenoh configuration (:func:`zenoh_config`), with a warning when the
    settings' zenoh file leaves a link's send queue for data shorter than
    :data:`TX_QUEUE_BATCHES` batches: with such a file, a router under load drops robots' samples
    where the service cannot count them (see :func:`session_config`).

    Zenoh's runtimes are the process's, read from ``ZENOH_RUNTIME`` when its first session opens:
    unless the environment sets it, this sets :data:`SERVICE_RUNTIME` for the service (and the
    processes a host starts, which inherit it); in a process that already opened a session it
    changes nothing."""
    os.environ.setdefault("ZENOH_RUNTIME", SERVICE_RUNTIME)
    cfg = zenoh_config(settings)
    short = short_queues(cfg) if settings.zenoh_config is not None else []
    if short:
        log.warning(
            "zenoh file %s: a link's send queue holds fewer batches than the %d the service "
            "sets without a file (%s); a router drops a robot's sample, unseen by the service, "
            "once a link's queue has been full for 1 ms (zenoh's default, 2 batches, is ~10 ms "
            "of 200 robots' scans): set transport.link.tx.queue.size.data and .data_high to %d",
            settings.zenoh_config,
            TX_QUEUE_BATCHES,
            ", ".join(short),
            TX_QUEUE_BATCHES,
        )
    return cfg


#: Seconds a stop waits for an open under way to end (a router's open takes about half a second
#: on a busy 2-core machine, the first of a process included).
OPEN_END_WAIT_S: Final = 2.0


class StoppedWaiting(RuntimeError):
    """The service was told to stop while its zenoh session was still opening."""


def open_unless_stopped(
    cfg: zenoh.Config, stop: threading.Event, endpoints: Sequence[str], say_after_s: float = 5.0
) -> zenoh.Session:
    """``zenoh.open(cfg)``, given up once ``stop`` is set.

    A client whose file waits for its router (``connect/timeout_ms: -1``, the deployment's
    ``service-client.json5``) stays in ``zenoh.open`` until a router answers, where the signal
    handlers never ran: SIGTERM and Ctrl-C did nothing (``docker compose stop``, a pod deleted:
    killed after the grace period) and the service said nothing meanwhile. The session is opened
    by a thread of its own; this waits on ``stop`` and says, after ``say_after_s``, that it waits
    for ``endpoints`` (the settings' ``connect``, the file's included: :func:`with_file`).

    Raises:
        StoppedWaiting: ``stop`` was set first. An open under way is given
            :data:`OPEN_END_WAIT_S` to end (what it opened is closed): a process that ended while
            its opening thread was still in zenoh's code aborted (exit -6, "FATAL: exception not
            rethrown") when that thread came back during the interpreter's end, which stops it by
            unwinding through zenoh's frames. One that waits for a router that does not answer is
            left to the process's end.
        zenoh.ZError: the session cannot be opened.
    """
    if stop.is_set():  # told to stop before (while the kernels compiled): no thread left in open
        raise StoppedWaiting("stopped before zenoh was opened")
    opened: Future[zenoh.Session] = Future()

    def opening() -> None:
        try:
            opened.set_result(zenoh.open(cfg))
        except BaseException as err:  # handed to the waiting thread
            opened.set_exception(err)

    threading.Thread(target=opening, name="zenoh-open", daemon=True).start()
    say_at = time.monotonic() + say_after_s
    while not opened.done():
        if stop.wait(0.1):
            _close_when_open(opened, OPEN_END_WAIT_S)
            raise StoppedWaiting("stopped while waiting for zenoh")
        if time.monotonic() > say_at:
            say_at = math.inf
            where = ", ".join(endpoints) or "its connect endpoints"
            log.warning("waiting for zenoh at %s to answer", where)
    return opened.result()


def _close_when_open(opened: Future[zenoh.Session], wait_s: float) -> None:
    """Wait up to ``wait_s`` for an open given up on, and close the session it opened."""
    try:
        session = opened.result(timeout=wait_s)
    except BaseException:  # still opening (left), or it failed: nothing to close
        return
    with contextlib.suppress(zenoh.ZError):
        session.close()


def short_queues(cfg: zenoh.Config) -> list[str]:
    """The data priorities whose links' send queue holds fewer than :data:`TX_QUEUE_BATCHES`
    batches in ``cfg``, as ``"data: 2"``."""
    short = []
    for priority in TX_QUEUE_PRIORITIES:
        try:
            batches = int(json.loads(cfg.get_json(f"transport/link/tx/queue/size/{priority}")))
        except (zenoh.ZError, ValueError, TypeError):
            continue
        if batches < TX_QUEUE_BATCHES:
            short.append(f"{priority}: {batches}")
    return short


def client_config(endpoint: str) -> zenoh.Config:
    """A client-mode zenoh configuration connecting to ``endpoint``, no scouting."""
    return session_config("client", connect=[endpoint])


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
