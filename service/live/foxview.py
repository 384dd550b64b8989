"""The live view: a Foxglove WebSocket server showing the running service, off its hot path.

An operator opens ``ws://ADDR:PORT`` in the Foxglove app ("Open connection", Foxglove WebSocket)
and sees, live, the channels a log's Foxglove views have (:mod:`service.logs.foxglove`, the same
converter and schemas): every map (``/foxglove/maps/{map_id}``), each robot's pose
(``/foxglove/robots/{robot}/pose``), initial pose and latest scan, the transforms map ->
``{robot}/base_link`` (``/foxglove/tf``, which puts each scan in the map frame), and one more:
``/foxglove/fleet`` (``foxglove.SceneUpdate``), each robot's 1-sigma ellipse and status label
(:mod:`service.live.foxstatus`), and ``/foxglove/maphealth/{map_id}``, each map's MapHealth drawn
over it (``added`` outlined in orange, ``removed`` walls in magenta). The server is the
maintained Foxglove SDK's (``foxglove-sdk``, protocol ``foxglove.sdk.v1``).

Cost to localization: :meth:`FoxgloveView.record`, called where the service records, keeps the
newest message per topic under a lock and returns. A thread of its own wakes ``rate_hz`` times
a second, converts what changed, but only for channels a client is subscribed to, and hands it
to the SDK (whose server runs on its own Rust threads). A robot's view is thus refreshed at most
``rate_hz`` times a second whatever its scan rate, and with no client connected the thread
converts nothing. A client that subscribes gets the newest message of that channel at the next
tick, maps included.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import foxglove
from foxglove import Channel, Context, Schema
from foxglove.websocket import ChannelView, Client, ServerListener

from service.keys import Keys
from service.live.foxstatus import maphealth_update, status_entity, status_update
from service.live.wsgate import Gate
from service.logs.foxglove import (
    FRAME_TRANSFORM,
    LASER_SCAN,
    POSE_IN_FRAME,
    SCENE_UPDATE,
    TF_TOPIC,
    FoxgloveConverter,
    embedded_dir,
)
from service.logs.mcapfile import Record
from service.logs.mcapread import robot_topic
from service.maps.book import MapBook

log = logging.getLogger(__name__)

FLEET_TOPIC = "/foxglove/fleet"
MAPHEALTH_SCHEMA = "rlutf.MapHealth"
MAPHEALTH_TOPIC = "/foxglove/maphealth"
#: The wire messages shown, by schema, and the Foxglove schema of each robot's own channel.
SOURCES = {
    "rlutf.LaserScan": ("scan", LASER_SCAN),
    "rlutf.PoseEstimate": ("pose", POSE_IN_FRAME),
    "rlutf.InitialPose": ("initialpose", POSE_IN_FRAME),
}
#: The shared channels each kind of message also feeds.
SHARED = {"scan": (), "pose": (TF_TOPIC, FLEET_TOPIC), "initialpose": (TF_TOPIC,)}


#: Lines of the Foxglove SDK's own log let through per :data:`SDK_LOG_WINDOW_S` (the rest are
#: counted, and the next line let through says how many were held back).
SDK_LOG_BURST = 20
SDK_LOG_WINDOW_S = 10.0


class _SdkLogLimit(logging.Handler):
    """Hands the SDK's log records (logger ``foxglove`` and below) on to the root logger's
    handlers, at most :data:`SDK_LOG_BURST` per :data:`SDK_LOG_WINDOW_S`.

    The SDK logs an ERROR line per malformed frame and per unknown channel of a subscribe: one
    16 MiB subscribe message from a client made 130,000 lines, 56 MB of log from one
    connection, and a client may reconnect for ever.
    """

    def __init__(self) -> None:
        super().__init__()
        self._window_end = 0.0
        self._let = 0
        self.held = 0  # records held back in this window (tests, figures)

    def emit(self, record: logging.LogRecord) -> None:
        now = time.monotonic()
        if now >= self._window_end:
            self._window_end, self._let = now + SDK_LOG_WINDOW_S, 0
        if self._let >= SDK_LOG_BURST:
            self.held += 1
            return
        self._let += 1
        if self.held:
            held = f"{self.held} lines of the Foxglove server held back"
            record.msg = f"{record.getMessage()} ({held})"
            record.args = None
            self.held = 0
        logging.getLogger().handle(record)


def _limit_sdk_log() -> None:
    """Route the SDK's log through :class:`_SdkLogLimit` (once per process)."""
    sdk = logging.getLogger("foxglove")
    if not any(isinstance(h, _SdkLogLimit) for h in sdk.handlers):
        sdk.addHandler(_SdkLogLimit())
        sdk.propagate = False


class LiveViewError(OSError):
    """The live view cannot listen: its port is in use or its address is not local."""


def robot_channel(robot: str, leaf: str) -> str:
    """The Foxglove topic of a robot's ``leaf`` (as in a log)."""
    return f"/foxglove/robots/{robot}/{leaf}"


class FoxgloveView:
    """A Foxglove WebSocket server fed with the newest message of each topic.

    Args:
        port: TCP port (0: any free one, see :attr:`url`).
        addr: address to listen on.
        maps: the service's maps (read at each tick: a new version is shown).
        keys: the key layout.
        rate_hz: how often the view is refreshed, per second.
        name: the server's name, shown by the Foxglove app.
    """

    def __init__(
        self,
        port: int,
        addr: str,
        maps: MapBook,
        keys: Keys,
        rate_hz: float = 10.0,
        name: str = "rlutf",
    ) -> None:
        self.port, self.addr, self.maps, self.keys = port, addr, maps, keys
        self.period_s = 1.0 / rate_hz
        self.name = name
        self._lock = threading.Lock()
        self._latest: dict[str, Record] = {}  # Zenoh key -> newest message
        self._dirty: set[str] = set()  # Zenoh keys to show at the next tick
        self._maps_shown: dict[str, int] = {}  # map id -> version shown
        self._health: dict[str, bytes] = {}  # {prefix}/maphealth/{map_id} -> newest, unshown
        self._health_latest: dict[str, bytes] = {}  # the same, shown or not
        self._resend_maps = False
        self._gone: set[str] = set()  # robots forgotten: their channels closed at the next tick
        self._channels: dict[str, Channel] = {}
        self._converter = FoxgloveConverter()
        self._context: Context | None = None
        self._server: Any = None
        self._gate: Gate | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.shown = 0  # messages handed to the server (tests, figures)

    # ------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Listen and start the refresh thread.

        Raises:
            LiveViewError: the port is in use or the address is not local.
        """
        _limit_sdk_log()
        self._context = Context()
        try:  # the SDK on a loopback port of its own, behind a door that bounds its clients
            self._gate = Gate(self.addr, self.port, 0)
        except OSError as err:
            raise LiveViewError(
                f"cannot serve the live view on {self.addr}:{self.port}: {err}"
            ) from err
        try:
            self._server = foxglove.start_server(
                name=self.name,
                host="127.0.0.1",
                port=0,
                context=self._context,
                server_listener=_Listener(self),
            )
        except RuntimeError as err:  # the SDK's FoxgloveError
            self._gate.close()
            raise LiveViewError(f"cannot start the live view's server: {err}") from err
        self._gate.target = self._server.port
        self._channel(TF_TOPIC, FRAME_TRANSFORM)
        self._channel(FLEET_TOPIC, SCENE_UPDATE)
        self._thread = threading.Thread(target=self._run, name="rlutf-foxglove", daemon=True)
        self._thread.start()
        log.info("foxglove live view on %s", self.url)

    @property
    def url(self) -> str | None:
        """``ws://ADDR:PORT`` once started."""
        if self._server is None or self._gate is None:
            return None
        host = f"[{self.addr}]" if ":" in self.addr else self.addr
        return f"ws://{host}:{self._gate.port}"

    def close(self) -> None:
        """Stop the thread and the server."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self._gate is not None:
            self._gate.close()
        if self._server is not None:
            self._server.stop()
            self._server = None

    # ------------------------------------------------------------------------ inputs
    def record(
        self, topic: str, schema_name: str, payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Keep the newest message of ``topic`` if it is one the view shows."""
        if schema_name == MAPHEALTH_SCHEMA:  # a map's MapHealth: drawn over the map
            with self._lock:
                self._health[topic] = self._health_latest[topic] = payload
            return
        if schema_name not in SOURCES:
            return
        with self._lock:
            self._latest[topic] = Record(topic, schema_name, payload, log_time_ns, publish_time_ns)
            self._dirty.add(topic)

    def forget(self, robot: str) -> None:
        """``robot`` left this service (evicted, handed over): drop its newest messages now,
        and at the next tick close its channels (unadvertised to the clients) and delete its
        entity on ``/foxglove/fleet``. Without it the view kept every robot it ever saw."""
        with self._lock:
            for leaf, _ in SOURCES.values():
                key = self.keys.robot(robot, leaf)
                self._latest.pop(key, None)
                self._dirty.discard(key)
            self._gone.add(robot)

    def subscribed(self, topic: str) -> None:
        """A client subscribed to ``topic``: show it the newest message at the next tick."""
        with self._lock:
            if topic.startswith("/foxglove/maps/"):
                self._resend_maps = True
            elif topic.startswith(MAPHEALTH_TOPIC + "/"):
                self._health.update(self._health_latest)
            elif topic in (TF_TOPIC, FLEET_TOPIC):
                self._dirty.update(t for t, r in self._latest.items() if r.schema_name != _SCAN)
            else:
                parts = topic.split("/")
                if len(parts) == 5 and parts[:3] == ["", "foxglove", "robots"]:
                    self._dirty.add(self.keys.robot(parts[3], parts[4]))

    # ------------------------------------------------------------------------ refresh thread
    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.tick()
            except Exception:  # the view is never worth stopping the service for
                log.exception("foxglove live view refresh failed")

    def tick(self) -> None:
        """Show what changed since the last tick (the refresh thread calls it)."""
        self._show_maps()
        self._show_health()
        with self._lock:
            gone, self._gone = self._gone, set()
            dirty, self._dirty = self._dirty, set()
            records = [self._latest[t] for t in dirty if t in self._latest]
        self._close_robots(gone)
        entities, latest = [], 0
        for rec in records:
            parts = robot_topic(rec.topic)
            if parts is None:
                continue
            leaf, _ = SOURCES[rec.schema_name]
            for kind, schema in SOURCES.values():  # advertised together at a robot's first sight
                self._channel(robot_channel(parts.robot, kind), schema)
            own = self._channels[robot_channel(parts.robot, leaf)]
            if not (own.has_sinks() or any(self._channels[t].has_sinks() for t in SHARED[leaf])):
                continue
            for out in self._converter(rec):
                self._channel(out.topic, out.schema_name).log(out.payload, log_time=out.log_time_ns)
                self.shown += 1
            if leaf == "pose" and self._channels[FLEET_TOPIC].has_sinks():
                pose = json.loads(rec.payload)
                frame = self._converter.frame_of(str(pose["map_id"]))
                entities.append(status_entity(parts.robot, pose, frame))
                latest = max(latest, rec.log_time_ns)
        if entities:
            self._channels[FLEET_TOPIC].log(status_update(entities), log_time=latest)
            self.shown += 1

    def _close_robots(self, gone: set[str]) -> None:
        """Close the channels of the robots forgotten, and delete their fleet entities."""
        deleted = []
        for robot in sorted(gone):
            for kind, _ in SOURCES.values():
                channel = self._channels.pop(robot_channel(robot, kind), None)
                if channel is not None:
                    channel.close()
                    deleted.append(f"robot/{robot}")
        fleet = self._channels.get(FLEET_TOPIC)
        if deleted and fleet is not None and fleet.has_sinks():
            now = time.time_ns()
            fleet.log(status_update([], sorted(set(deleted)), now), log_time=now)

    def _show_maps(self) -> None:
        with self._lock:
            resend, self._resend_maps = self._resend_maps, False
        for map_id in self.maps.ids():
            loaded = self.maps.get(map_id)
            if loaded is None or (not resend and self._maps_shown.get(map_id) == loaded.version):
                continue
            self._maps_shown[map_id] = loaded.version
            if not self._channel(f"/foxglove/maps/{map_id}", SCENE_UPDATE).has_sinks():
                # Advertised, converted when a client subscribes (a 10 MB map took 1.4 s of this
                # process's CPU, its lock held up to 81 ms at a time, for no one watching).
                self._converter.note_frame(map_id, loaded.payload)
                continue
            t = loaded.received_ns
            rec = Record(self.keys.map(map_id), "rlutf.Map", loaded.payload, t, t)
            for out in self._converter(rec):
                self._channel(out.topic, out.schema_name).log(out.payload, log_time=t)
                self.shown += 1

    def _show_health(self) -> None:
        """Each map's newest MapHealth on ``/foxglove/maphealth/{map_id}`` (a SceneUpdate)."""
        with self._lock:
            health, self._health = self._health, {}
        for payload in health.values():
            data = json.loads(payload)
            map_id = str(data["map_id"])
            channel = self._channel(f"{MAPHEALTH_TOPIC}/{map_id}", SCENE_UPDATE)
            if not channel.has_sinks():  # advertised; drawn when a client subscribes
                continue
            update = maphealth_update(data, self._converter.frame_of(map_id))
            channel.log(update, log_time=int(data["stamp_ns"]))
            self.shown += 1

    def _channel(self, topic: str, schema_name: str) -> Channel:
        """The channel of ``topic``, advertised to clients the first time it is asked for."""
        ch = self._channels.get(topic)
        if ch is None:
            ch = Channel(
                topic,
                schema=_schema(schema_name),
                message_encoding="json",
                context=self._context,
            )
            self._channels[topic] = ch
        return ch


class _Listener(ServerListener):
    """The SDK's callbacks (on its threads); the SDK's defaults for the others."""

    def __init__(self, view: FoxgloveView) -> None:
        self.view = view

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        """Show the new subscriber the channel's newest message."""
        self.view.subscribed(channel.topic)


_SCAN = "rlutf.LaserScan"
_SCHEMAS: dict[str, Schema] = {}


def _schema(name: str) -> Schema:
    """Foxglove's JSON Schema of ``name``, as the log embeds it."""
    schema = _SCHEMAS.get(name)
    if schema is None:
        data = (embedded_dir() / f"{name}.json").read_bytes()
        schema = _SCHEMAS[name] = Schema(name=name, encoding="jsonschema", data=data)
    return schema
