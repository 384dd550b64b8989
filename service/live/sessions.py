"""Zenoh session configurations: the service's, a client's, and a free loopback port.

One home for the keys every configuration sets (``mode``, ``listen/endpoints``,
``connect/endpoints``, ``scouting/multicast/enabled``), so the service, the demo, the tests and
the benchmarks open sessions the same way.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence
from pathlib import Path

import zenoh

from service.config import Settings


def session_config(
    mode: str,
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    file: Path | None = None,
) -> zenoh.Config:
    """A zenoh configuration: ``file`` if given, then these settings on top.

    Without a file, zenoh's shared-memory transport is off: with it on, every session on this
    host that puts a message over 3 kB makes a 16 MB shared pool that each session it reaches
    maps, which is resident memory in both (20 simulated robots on one host took a router from
    67 to 394 MB); over the network it does nothing. With a file, the file decides (zenoh's
    default: on).

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


def client_config(endpoint: str) -> zenoh.Config:
    """A client-mode zenoh configuration connecting to ``endpoint``, no scouting."""
    return session_config("client", connect=[endpoint])


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
