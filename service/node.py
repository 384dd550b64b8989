"""The localization service on a Zenoh session.

Wiring only: callbacks decode, validate, record and hand inputs to the :class:`Dispatcher`;
finished batches are published and recorded; maps are fetched and followed on a thread of their
own. The computation is :class:`service.engine.FleetEngine`, the same code replay runs.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from schemas import (
    SCHEMA_NAMES,
    Event,
    EventCode,
    InitialPose,
    LaserScan,
    Map,
    Odometry,
    PoseEstimate,
    SchemaError,
    decode,
    encode,
)
from service.config import Settings
from service.dispatch import MODELS, Dispatcher, Done
from service.keys import INPUT_KINDS, KeyError_, Keys
from service.maps import LoadedMap, MapBook, MapRejected
from service.recording import NullRecorder, Recorder
from service.stats import Stats
from service.store import FileMapStore, MapStorage

log = logging.getLogger(__name__)

SCHEMA_OF_LEAF = {
    "scan": SCHEMA_NAMES[LaserScan],
    "odom": SCHEMA_NAMES[Odometry],
    "initialpose": SCHEMA_NAMES[InitialPose],
    "pose": SCHEMA_NAMES[PoseEstimate],
    "events": SCHEMA_NAMES[Event],
}
MAP_SCHEMA = SCHEMA_NAMES[Map]
EVENT_SCHEMA = SCHEMA_NAMES[Event]
JSON = zenoh.Encoding.APPLICATION_JSON


def zenoh_config(settings: Settings) -> zenoh.Config:
    """A zenoh configuration from the settings (file first, then the flags on top)."""
    cfg = (
        zenoh.Config.from_file(str(settings.zenoh_config))
        if settings.zenoh_config
        else (zenoh.Config())
    )
    cfg.insert_json5("mode", json.dumps(settings.mode))
    if settings.listen and settings.mode != "client":
        cfg.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.connect:
        cfg.insert_json5("connect/endpoints", json.dumps(settings.connect))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    return cfg


class _Clock:
    """Strictly increasing receive times (ns since the epoch), so log order is total."""

    def __init__(self) -> None:
        self._last = 0
        self._lock = threading.Lock()

    def __call__(self) -> int:
        with self._lock:
            now = max(time.time_ns(), self._last + 1)
            self._last = now
            return now


class LocalizationService:
    """One instance of the service.

    Args:
        settings: effective configuration.
        recorder: where to record; ``None`` records nothing.
        session: an open Zenoh session to use (tests); by default one is opened from the
            settings and closed with the service.
    """

    def __init__(
        self,
        settings: Settings,
        recorder: Recorder | None = None,
        session: zenoh.Session | None = None,
    ) -> None:
        self.settings = settings
        self.keys = Keys(settings.prefix)
        self.recorder: Recorder = recorder or NullRecorder()
        self.stats = Stats(settings.instance)
        self.clock = _Clock()
        self.maps = MapBook(settings.max_payload_bytes)
        self._own_session = session is None
        self._session = session
        self._poses: dict[str, bytes] = {}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        self._map_tasks: queue.Queue[tuple[str, str, bytes, int] | None] = queue.Queue()
        self._fetching: dict[str, float] = {}
        self._declared: list[Any] = []
        self._input_sub: Any = None
        self._storage: MapStorage | None = None
        self._map_thread: threading.Thread | None = None
        self.dispatcher = Dispatcher(
            self.keys,
            settings.localizer,
            settings.workers,
            int(settings.event_interval_s * 1e9),
            self._on_done,
            self._on_drop,
        )
        self.closed = threading.Event()

    # ------------------------------------------------------------------------ lifecycle
    @property
    def session(self) -> zenoh.Session:
        """The Zenoh session (open after :meth:`start`)."""
        if self._session is None:
            raise RuntimeError("the service is not started")
        return self._session

    def start(self) -> LocalizationService:
        """Start workers, open the session and declare everything."""
        s = self.settings
        self.recorder.set_config(s.effective())
        self.dispatcher.start()
        if self._session is None:
            self._session = zenoh.open(zenoh_config(s))
        session = self._session
        if not s.no_store:
            self._storage = MapStorage(
                session,
                self.keys,
                FileMapStore(s.store_dir),
                s.max_payload_bytes,
                on_error=lambda key, msg: self._global_event(
                    "error", EventCode.INVALID_MAP, key, msg
                ),
            )
        self._map_thread = threading.Thread(target=self._map_worker, name="rlutf-maps", daemon=True)
        self._map_thread.start()
        self._declared += [
            session.declare_subscriber(self.keys.maps, self._on_map_sample),
            session.declare_queryable(self.keys.all_poses, self._on_pose_query, complete=False),
            session.declare_queryable(self.keys.health(s.instance), self._on_health_query),
            session.liveliness().declare_token(self.keys.service(s.instance)),
        ]
        self._input_sub = session.declare_subscriber(self.keys.robots_inputs, self._on_robot_sample)
        log.info("rlutf service %s started (mode %s, prefix %s)", s.instance, s.mode, s.prefix)
        return self

    def close(self) -> None:
        """Graceful stop: no more input, finish in-flight updates, flush, close the session."""
        if self.closed.is_set():
            return
        self.closed.set()
        if self._input_sub is not None:
            self._input_sub.undeclare()
        self.dispatcher.stop()
        self._map_tasks.put(None)
        if self._map_thread is not None:
            self._map_thread.join(5.0)
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        for pub in self._publishers.values():
            pub.undeclare()
        if self._storage is not None:
            self._storage.close()
        self.recorder.close()
        if self._own_session and self._session is not None:
            self._session.close()
        log.info("rlutf service %s stopped", self.settings.instance)

    def __enter__(self) -> LocalizationService:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------ inputs
    def _on_robot_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        received = self.clock()
        try:
            parsed = self.keys.parse_robot_key(key)
        except KeyError_ as err:
            self.stats.add("received")
            self.stats.add("rejected")
            self._global_event("error", EventCode.INVALID_KEY, key, str(err), received)
            return
        if parsed is None:
            return
        robot, leaf = parsed
        if leaf not in INPUT_KINDS:
            return  # our own poses and events, or keys of other tools
        self.stats.add("received")
        payload = sample.payload.to_bytes()
        try:
            msg = decode(MODELS[leaf], payload, max_bytes=self.settings.max_payload_bytes)
        except SchemaError as err:
            self.stats.add("rejected")
            self._robot_event(robot, "error", EventCode.INVALID_MESSAGE, key, str(err), received)
            return
        self.recorder.record(key, SCHEMA_OF_LEAF[leaf], payload, received, msg.stamp_ns)
        self.dispatcher.submit(robot, leaf, payload, msg, received)

    def _on_map_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        key = str(sample.key_expr)
        try:
            map_id = self.keys.parse_map_key(key)
        except KeyError_ as err:
            self._global_event("error", EventCode.INVALID_KEY, key, str(err))
            return
        if map_id is not None:
            self._map_tasks.put(("offer", map_id, sample.payload.to_bytes(), 0))

    # ------------------------------------------------------------------------ maps
    def _map_worker(self) -> None:
        while True:
            task = self._map_tasks.get()
            if task is None:
                return
            kind, map_id, payload, _ = task
            try:
                if kind == "offer":
                    self._offer_map(map_id, payload)
                else:
                    self._fetch_map(map_id, payload.decode())
            except Exception:
                log.exception("map task %s %s failed", kind, map_id)

    def _offer_map(self, map_id: str, payload: bytes) -> bool:
        key = self.keys.map(map_id)
        # Order matters for replay: the map is recorded and reaches the shards at one instant
        # of the receive clock, before any input received after it.
        with self.dispatcher.lock:
            received = self.clock()
            try:
                loaded = self.maps.offer(map_id, payload, received)
            except MapRejected as err:
                loaded = None
                error: str | None = str(err)
            else:
                error = None
            if loaded is not None:
                self._record_map(loaded)
        if error is not None:
            self._global_event("error", EventCode.INVALID_MAP, key, error, received)
            return False
        if loaded is None:
            return True
        self.dispatcher.broadcast_map(loaded)
        self._global_event(
            "info",
            EventCode.MAP_UPDATED,
            key,
            f"map {map_id} version {loaded.version} loaded",
            received,
        )
        return True

    def _record_map(self, loaded: LoadedMap) -> None:
        self.recorder.record(
            self.keys.map(loaded.map_id),
            MAP_SCHEMA,
            loaded.payload,
            loaded.received_ns,
            loaded.received_ns,
        )

    def _fetch_map(self, map_id: str, robot: str) -> None:
        now = time.monotonic()
        if self.maps.get(map_id) is not None:
            return
        if now - self._fetching.get(map_id, -1e9) < 1.0:
            return
        self._fetching[map_id] = now
        key = self.keys.map(map_id)
        found = False
        for reply in self.session.get(key, timeout=self.settings.map_timeout_s):
            if reply.ok is None:
                continue
            found = self._offer_map(map_id, reply.ok.payload.to_bytes()) or found
        if not found:
            self._robot_event(
                robot,
                "error",
                EventCode.MAP_NOT_FOUND,
                key,
                f"no storage answered for map {map_id!r}",
            )

    # ------------------------------------------------------------------------ outputs
    def _on_done(self, done: Done) -> None:
        self.stats.compute(done.compute_s * 1e3)
        for out in done.outputs:
            if out.kind == "need_map":
                assert out.map_id is not None
                self._map_tasks.put(("fetch", out.map_id, done.robot.encode(), 0))
                continue
            if out.kind == "pose":
                self._poses[done.robot] = out.payload
                self._publish(out.key, out.payload, pose=True)
                now = self.clock()
                self.recorder.record(
                    out.key, SCHEMA_OF_LEAF["pose"], out.payload, now, out.stamp_ns
                )
                self.stats.add("processed")
                if out.received_ns is not None:
                    self.stats.latency((now - out.received_ns) / 1e6)
                if out.status == "lost":
                    self.stats.add("lost")
            else:
                self._publish(out.key, out.payload)
                self.recorder.record(out.key, EVENT_SCHEMA, out.payload, self.clock(), out.stamp_ns)

    def _on_drop(self, robot: str, stamp_ns: int, received_ns: int) -> None:
        # Recorded (not published: under overload that would add load) so replay drops the
        # same scans; counted in health.
        ev = Event(
            stamp_ns=stamp_ns,
            level="info",
            code=EventCode.SCAN_DROPPED,
            key=self.keys.robot(robot, "scan"),
            message=f"scan {stamp_ns} replaced by a newer scan before processing",
        )
        self.recorder.record(
            self.keys.robot_events(robot), EVENT_SCHEMA, encode(ev), self.clock(), stamp_ns
        )

    def _publish(self, key: str, payload: bytes, pose: bool = False) -> None:
        if self.closed.is_set() and self._session is None:
            return
        try:
            if pose:
                pub = self._publishers.get(key)
                if pub is None:
                    with self._lock:
                        pub = self._publishers.get(key)
                        if pub is None:
                            pub = self.session.declare_publisher(
                                key,
                                encoding=JSON,
                                congestion_control=zenoh.CongestionControl.DROP,
                                priority=zenoh.Priority.DATA_HIGH,
                                express=True,
                            )
                            self._publishers[key] = pub
                pub.put(payload)
            else:
                self.session.put(key, payload, encoding=JSON)
        except zenoh.ZError:
            log.warning("could not publish on %s", key, exc_info=True)

    def _event(
        self, key: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        stamp = now if now is not None else self.clock()
        ev = Event(stamp_ns=stamp, level=level, code=code, key=about, message=message)
        payload = encode(ev)
        log.log(
            logging.WARNING if level in ("warning", "error") else logging.INFO,
            "%s %s: %s",
            code,
            about,
            message,
        )
        self._publish(key, payload)
        self.recorder.record(key, EVENT_SCHEMA, payload, self.clock(), stamp)

    def _robot_event(
        self, robot: str, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        self._event(self.keys.robot_events(robot), level, code, about, message, now)

    def _global_event(
        self, level: str, code: str, about: str, message: str, now: int | None = None
    ) -> None:
        self._event(self.keys.events, level, code, about, message, now)

    # ------------------------------------------------------------------------ queries
    def _on_pose_query(self, query: zenoh.Query) -> None:
        with query:
            ke = query.key_expr
            for robot, payload in list(self._poses.items()):
                key = self.keys.pose(robot)
                if ke.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, payload, encoding=JSON)

    def health(self) -> bytes:
        """The current Health message, encoded."""
        extra: dict[str, Any] = {
            "pending_inputs": self.dispatcher.pending(),
            "workers": len(self.dispatcher.shards) if self.dispatcher.processes else 0,
            "recorder_overflow": self.recorder.overflowed,
            "maps": sorted(self.maps_held()),
        }
        return encode(self.stats.health(len(self._poses), self.dispatcher.dropped, extra))

    def maps_held(self) -> list[str]:
        """Ids of the maps loaded."""
        return self.maps.ids()

    def _on_health_query(self, query: zenoh.Query) -> None:
        with query:
            query.reply(self.keys.health(self.settings.instance), self.health(), encoding=JSON)

    def wait(self, stop: threading.Event, tick: Callable[[], None] | None = None) -> None:
        """Block until ``stop`` is set, calling ``tick`` about once a second."""
        while not stop.wait(1.0):
            if tick is not None:
                tick()
