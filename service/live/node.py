"""The localization service on a Zenoh session.

Wiring only: callbacks decode, validate, record and hand inputs to the :class:`Dispatcher`;
finished batches are published and recorded; maps are fetched and followed on a thread of their
own (:mod:`service.live.mapfeed`). The computation is :class:`service.engine.FleetEngine`.

Scale-out: instances sharing a prefix split the fleet by rendezvous hashing over their
liveliness tokens (:mod:`service.cluster.membership`); each localizes, records, counts and
answers pose queries for the robots it owns only, and seeds a robot it takes over from its last
published pose (:mod:`service.cluster.ownership`); they share map health evidence.

ROS 2 robots (``settings.ros2.enabled``) come in through :class:`service.ros2.frontdoor.
Ros2FrontDoor` on the same session: once validated, their inputs take the JSON inputs' path
(recorded as JSON), and their poses also go out as ROS messages.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import zenoh

from schemas import (
    SCHEMA_NAMES,
    Event,
    EventCode,
    InitialPose,
    LaserScan,
    Odometry,
    PoseEstimate,
    Relocalize,
    encode,
)
from service.cluster.membership import Membership, fetch_last_pose, fetch_poses
from service.cluster.names import NameClaim
from service.cluster.ownership import Ownership
from service.cluster.posestate import NullPoseState, PoseKeeper, PoseState
from service.config import Settings
from service.guard import check_input
from service.keys import InputKind, Keys, Message
from service.live.admission import Gate, Sweeper
from service.live.clock import ReceiveClock
from service.live.dispatch import Dispatcher
from service.live.healthfeed import HealthFeed
from service.live.intake import Intake
from service.live.keywatch import KeyWatch
from service.live.liveview import LiveView, make_live_view
from service.live.loop import Inputs
from service.live.mapfeed import MapFeed
from service.live.memory import HeapTrimmer
from service.live.metrics import make_metrics
from service.live.outbox import Outbox
from service.live.publishing import EVENT_SCHEMA, Announcer
from service.live.robots import PLACING, RobotView, robots_key
from service.live.sessions import open_unless_stopped, service_config
from service.live.shards import Done
from service.live.stats import Stats
from service.live.supervise import worker_lost
from service.live.warmaside import warm_up_aside
from service.live.worker import Entry
from service.logs.recording import NullRecorder, Recorder
from service.maps.book import MapBook
from service.maps.files import FileMapStore
from service.maps.store import MapStorage

log = logging.getLogger(__name__)

SCHEMA_OF_LEAF = {
    "scan": SCHEMA_NAMES[LaserScan],
    "odom": SCHEMA_NAMES[Odometry],
    "initialpose": SCHEMA_NAMES[InitialPose],
    "relocalize": SCHEMA_NAMES[Relocalize],
    "pose": SCHEMA_NAMES[PoseEstimate],
    "events": SCHEMA_NAMES[Event],
}
JSON = zenoh.Encoding.APPLICATION_JSON


class LocalizationService:
    """One instance of the service.

    Args:
        settings: effective configuration.
        recorder: where to record; ``None`` records nothing.
        session: an open Zenoh session to use (tests); by default one from the settings.
        stop: set when the service is told to stop (the CLI's signal handler), before
            :meth:`close` runs: a worker process the same signal ended is not replaced. The
            service sets it itself when another instance takes its name (:meth:`wait` returns).
    """

    def __init__(
        self,
        settings: Settings,
        recorder: Recorder | None = None,
        session: zenoh.Session | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        self.settings = settings
        self.keys = Keys(settings.prefix)
        self.recorder: Recorder = recorder or NullRecorder()
        self.metrics = make_metrics(settings.instance, settings.metrics_port, settings.metrics_addr)
        self.stats = Stats(settings.instance, timings=self.metrics)
        self.clock = ReceiveClock()
        # Maps checked in a child process, sent back if robots run here (service.maps.book.MapBook)
        apart, own = settings.workers != 0 or settings.intake == "loop", settings.workers == 0
        self.maps = MapBook(settings.max_map_bytes, settings.map_limits(), apart, own)
        self.live: LiveView = make_live_view(settings, self.maps)  # Foxglove, or nothing
        self._own_session = session is None
        self._session = session
        self._poses: dict[str, bytes] = {}
        view = RobotView(settings.instance, self._poses, self.clock, settings.prefix)
        self.robot_view = view
        view.unplaced_ns = max(view.unplaced_ns, 3 * int(settings.event_interval_s * 1e9))
        self._declared: list[Any] = []
        self.outbox = Outbox()  # Events go out from its thread, never from a callback's
        self.out = Announcer(self.keys, self.recorder, self.clock, self.outbox, view.told)
        self._publish = self.out.publish
        self._robot_event = self.out.robot_event
        self._global_event = self.out.global_event
        self._on_drop = self.out.on_drop
        self.ready = False
        self.intake = Intake(self)
        self.stopping = stop if stop is not None else threading.Event()  # also: name lost
        self.name_claim = NameClaim(settings.instance, self.keys, self._name_taken)
        self._token: Any = None
        self._storage: MapStorage | None = None
        self.dispatcher = Dispatcher(
            self.keys,
            settings.localizer,
            settings.workers,
            int(settings.event_interval_s * 1e9),
            self._on_done,
            self._on_drop,
            threads=settings.worker_threads,
            nice=settings.worker_nice,
            clock=self.clock,
            on_seed=self._record_seed,
            on_lost=self._on_worker_lost,
            limits=settings.limits,
            map_health=settings.map_health,
            loop=settings.intake == "loop",
            poses=self.out,
            stop=self.stopping,
        )
        on_sample, wait_s = self.intake.on_robot_sample, settings.intake_wait_s
        self.inputs = Inputs(on_sample, self.dispatcher.loop, settings.intake, self.out, wait_s)
        self.mapfeed = MapFeed(
            self.keys,
            self.maps,
            self.dispatcher,
            self.recorder,
            self.clock,
            settings.map_timeout_s,
            self._global_event,
            self._robot_event,
            settings.event_interval_s,
        )
        self.membership = Membership(settings.instance)
        self.ownership = Ownership(
            self.membership,
            self._admit,
            self.clock,
            int(settings.handover_odom_s * 1e9),
            on_release=self._forget_pose,
            resume_max_age_ns=int(settings.resume_max_age_s * 1e9),
        )
        self.posestate: PoseKeeper = (  # restarts resume from it (service.cluster.posestate)
            NullPoseState()
            if settings.no_state
            else PoseState(
                settings.state_dir,
                settings.instance,
                settings.state_interval_s,
                self.clock,
                settings.max_payload_bytes,
                lambda level, code, msg: self._global_event(level, code, self.keys.events, msg),
            )
        )
        owns_key = lambda key: self.ownership.ready and self.membership.owns_key(key)  # noqa: E731
        self.keywatch = KeyWatch(self.keys, self._global_event, self.clock, settings, owns_key)
        self.ros2 = self.intake.front_door() if settings.ros2.enabled else None
        self.gate = Gate(
            self.clock,
            int(settings.max_stamp_ahead_s * 1e9),
            settings.max_robots,
            int(settings.event_interval_s * 1e9),
        )
        self.ownership.followed.max_ahead_ns = self.gate.max_ahead_ns
        self.ownership.followed.max_robots = settings.max_robots
        self.sweeper = Sweeper(
            self.clock, int(settings.robot_idle_s * 1e9), self.dispatcher.idle_since, self._evict
        )
        self.sweeper.also = self.out.say_folded  # the Events the budget held back, counted

        def rec(key: str, schema: str, payload: bytes, at: int, stamp: int) -> None:
            self.recorder.record(key, schema, payload, at, stamp)
            self.live.record(key, schema, payload, at, stamp)  # drawn in the live view

        self.healthfeed = HealthFeed(self.keys, self.maps, self._publish, rec, self.clock)
        self.healthfeed.share_as(settings.instance, settings.max_map_bytes, owns_key, self.keywatch)
        self.closed = threading.Event()

    # ------------------------------------------------------------------------ lifecycle
    @property
    def session(self) -> zenoh.Session:
        """The Zenoh session (open after :meth:`start`)."""
        if self._session is None:
            raise RuntimeError("the service is not started")
        return self._session

    def start(self, progress: Callable[[str], None] | None = None) -> LocalizationService:
        """Start workers, open the session and declare everything; return once ready.

        Ready means that every process of the instance can localize: the liveliness token
        (which routes robots here) is declared, and Health says ``ready``, only then.

        Args:
            progress: told what the start waits for when it takes more than a few seconds (the
                first start after an install compiles the localizer's kernels).
        """
        s = self.settings
        self.metrics.start(self)  # first: a port in use fails the start before anything runs
        self.live.start()
        # Compile the localizer's kernels (or load them from numba's cache) now, not at the
        # first scan. Worker processes do it as they start; with them, this process never runs
        # an update, and loaded kernels cost ~60 MB of resident memory a process.
        if not self.dispatcher.processes:
            warm_up_aside(progress, self.stopping)  # a child compiles on a first start
        self.recorder.set_config(s.effective())
        if hasattr(self.recorder, "on_event"):
            # In the log when it can be; published and logged so operators see it live.
            self.recorder.on_event = self.out.recorder_event
        self.dispatcher.start(progress)
        if self._session is None:
            self._session = open_unless_stopped(service_config(s), self.stopping, s.connect)
        session = self._session
        # Before anything is declared or recorded: refuses a name another instance has.
        self.name_claim.take(session, s.handover_timeout_s, stop=self.stopping)
        self.outbox.start(session)
        self.out.attach(session)
        if not s.no_store:
            self._storage = self.mapfeed.embed_store(
                session,
                FileMapStore(s.store_dir),
                s.max_map_bytes,
                lambda kind, level, code, key, text: self.keywatch.limited(
                    kind, level, code, key, text, self.clock()
                ),
            )
        else:
            self._declared.append(
                session.declare_subscriber(self.keys.maps, self.mapfeed.on_sample)
            )
        self.mapfeed.start(session)
        view = self.robot_view
        view.owns = self.ownership.owns
        self._declared += [
            session.declare_queryable(self.keys.all_poses, view.on_pose_query, complete=False),
            session.declare_queryable(self.keys.health(s.instance), self._on_health_query),
            session.declare_queryable(robots_key(s.prefix, s.instance), view.on_query),
            session.declare_queryable(self.keys.all_maphealth, self.healthfeed.on_query),
            self.healthfeed.declare(session),  # the other instances' map health evidence
        ]
        restored, problems = self.posestate.open()  # the poses kept across a restart
        for problem in problems:
            self._global_event("warning", EventCode.STATE_UNREADABLE, self.keys.events, problem)
        for r in restored:  # seed the robots at their first input (Ownership.restore)
            self.ownership.restore(r.pose, r.odometry, r.published_ns)
            view.restore(r.pose, r.published_ns)  # shown until then
        for r in {r.pose.map_id: r for r in restored}.values():  # load their maps now
            self.mapfeed.need(r.pose.map_id, r.pose.robot_id)
        # Follow the fleet first and join last, so robots that move here can be seeded.
        # One subscription for every robot key, in arrival order (service.live.loop.Inputs).
        if s.intake == "loop":  # its keys declared from the loop's thread (not a callback)
            self.intake.declare_keys(session)
        self.inputs.start(session, self.keys.robots_inputs)
        self.keywatch.start(session, self.stats)  # Events for keys nothing else takes
        if self.ros2 is not None:
            self.ros2.start(session)
        timeout, limit = s.handover_timeout_s, s.max_payload_bytes
        self.ownership.start(
            partial(fetch_last_pose, session, self.keys, timeout=timeout, max_bytes=limit)
        )
        self.membership.start(session, self.keys, timeout)
        if joining := len(self.membership.members) > 1:
            known = fetch_poses(session, self.keys, self.keys.all_poses, timeout, limit)
            self.ownership.remember(*known.values())
            for pose in {p.map_id: p for p in known.values()}.values():  # load the maps now
                self.mapfeed.need(pose.map_id, pose.robot_id)
            time.sleep(s.join_warmup_s)
        self.name_claim.confirm()  # one of this name claimed it first, seen since: no start
        self._token = session.liveliness().declare_token(self.keys.service(s.instance))
        self.ownership.grace_until = time.monotonic() + s.join_grace_s if joining else 0.0
        self.ownership.ready = True
        self.sweeper.start()
        self.ready = True
        log.info("rlutf service %s started (mode %s, prefix %s)", s.instance, s.mode, s.prefix)
        return self

    def close(self) -> None:
        """Graceful stop: no more input, finish in-flight updates, flush, close the session."""
        if self.closed.is_set():
            return
        self.closed.set()
        if self._token is not None:
            self._token.undeclare()  # the other instances take the robots over at once
        self.inputs.close()
        self.sweeper.close()
        self.dispatcher.stop()
        self.posestate.close()  # after the last pose is out
        if self.ros2 is not None:
            self.ros2.close()
        self.ownership.close()
        self.membership.close()
        self.name_claim.close()  # after the member token: the name is given up last
        self.mapfeed.close()
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self.keywatch.close()
        self.out.close()
        if self._storage is not None:
            self._storage.close()
        self.outbox.close()
        self.recorder.close()
        self.live.close()
        self.metrics.close()
        if self._own_session and self._session is not None:
            self._session.close()
        log.info("rlutf service %s stopped", self.settings.instance)

    def __enter__(self) -> LocalizationService:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------ inputs
    def robots_held(self) -> int:
        """Robots with a mailbox here or waiting for their seed (the gate's bound)."""
        return len(self.dispatcher.boxes) + self.ownership.acquiring()

    def holds(self, robot: str) -> bool:
        """Whether ``robot`` is held here."""
        return robot in self.dispatcher.boxes or self.ownership.holds(robot)

    def _evict(self, robot: str, why: str) -> bool:
        """Drop a robot that sent nothing for long (see service.live.admission)."""
        with self.ownership.lock:  # no input of the robot is admitted meanwhile
            if not self.dispatcher.forget(robot):
                return False
            self.ownership.forget(robot)
            self._forget_pose(robot)  # and in the live view
            self.posestate.forget(robot)
            if self.ros2 is not None:  # its tokens and publishers go
                self.ros2.forget(robot)
            self._robot_event(
                robot,
                "info",
                EventCode.ROBOT_EVICTED,
                self.keys.robot(robot, "scan"),
                why,
            )
        return True

    def _admit(self, robot: str, kind: InputKind, payload: bytes, msg: Message, at: int) -> None:
        """Record an input received at ``at`` (or a handover seed) and hand it to its mailbox."""
        key = self.keys.robot(robot, kind)
        self.recorder.record(key, SCHEMA_OF_LEAF[kind], payload, at, msg.stamp_ns)
        self.live.record(key, SCHEMA_OF_LEAF[kind], payload, at, msg.stamp_ns)
        self.dispatcher.submit(robot, kind, payload, msg, at)
        if kind == "odom":
            self.posestate.odom(robot, msg.stamp_ns, payload)
        elif kind in PLACING and check_input(msg, self.settings.limits) is None:
            self.robot_view.initialized(robot, at, getattr(msg, "map_id", None))  # not if refused

    def _record_seed(self, robot: str, entry: Entry) -> None:
        """Record an input made to re-seed a robot whose worker died (dispatcher lock held)."""
        key = self.keys.robot(robot, entry.kind)
        self.recorder.record(
            key, SCHEMA_OF_LEAF[entry.kind], entry.payload, entry.received_ns, entry.stamp_ns
        )

    def _on_worker_lost(self, index: int, code: int | None, robots: list[str]) -> None:
        about = self.keys.service(self.settings.instance)
        self._global_event("error", EventCode.WORKER_LOST, about, worker_lost(index, code, robots))

    def _name_taken(self, message: str) -> None:
        """Another instance of this name claimed it first (seen after the start): this one
        takes no more input, says what it did and stops (service.cluster.names)."""
        self.ownership.ready = False  # its robots are the other's: no input taken from now on
        did = f"it localized {self.stats.processed} scans since it started, {len(self._poses)}"
        about, code = self.keys.service(self.settings.instance), EventCode.INSTANCE_NAME_TAKEN
        self._global_event("error", code, about, f"{message}; {did} robots")
        self.stopping.set()

    def _forget_pose(self, robot: str) -> None:
        self._poses.pop(robot, None)
        self.robot_view.forget(robot)
        self.live.forget(robot)

    # ------------------------------------------------------------------------ outputs
    def _on_done(self, done: Done) -> None:
        self.stats.compute(done.compute_s * 1e3)
        for out in done.outputs:
            if out.kind == "need_map":
                assert out.map_id is not None
                self.mapfeed.need(out.map_id, done.robot)
                continue
            if out.kind in ("skipped", "rejected"):  # rejected: over a limit (service.guard)
                self.stats.add(out.kind)
                continue
            if out.kind == "evidence":
                self.healthfeed.on_evidence(out.evidence)
                continue
            if out.kind == "pose":
                with self.ownership.lock:  # a robot released meanwhile is not answered for
                    if self.ownership.active(done.robot):
                        self._poses[done.robot] = out.payload
                # Poses are not delivered back to this session's own subscriber (see _publish):
                # follow our own here, for a robot that comes back after a handover.
                self.ownership.follow_own_pose(done.robot, out.payload, out.stamp_ns)
                self._publish(out.key, out.payload, pose=True)
                if self.ros2 is not None:
                    self.ros2.on_pose(done.robot, out.payload)
                now = self.clock()
                self.posestate.pose(done.robot, out.payload, out.stamp_ns, now)
                self.recorder.record(
                    out.key, SCHEMA_OF_LEAF["pose"], out.payload, now, out.stamp_ns
                )
                self.live.record(out.key, SCHEMA_OF_LEAF["pose"], out.payload, now, out.stamp_ns)
                self.stats.add("processed")
                if out.received_ns is not None:
                    self.stats.latency((now - out.received_ns) / 1e6)
                if out.status == "lost":
                    self.stats.add("lost")
                self.robot_view.published(done.robot, now, out.received_ns)
                self.metrics.pose(out.status)
            else:
                self.out.engine_event(done.robot, out.key, out.payload)  # within the budget
                now = self.clock()
                self.recorder.record(out.key, EVENT_SCHEMA, out.payload, now, out.stamp_ns)
                self.robot_view.event(done.robot, out.payload, now)
                self.stats.count_event(out.payload)

    # ------------------------------------------------------------------------ queries
    def health(self) -> bytes:
        """The current Health message, encoded."""
        extra: dict[str, Any] = {
            "pending_inputs": self.dispatcher.pending(),
            "workers": self.dispatcher.alive_workers(),
            "workers_replaced": self.dispatcher.workers_replaced,
            "robots_reseeded": self.dispatcher.reseeded,
            "events_unsent": self.outbox.dropped,
            "recorder_overflow": self.recorder.overflowed,
            "recorder_queue": self.recorder.queued,
            "recorder_unrecorded": self.recorder.unrecorded,
            "maps": sorted(self.maps_held())[:50],  # a summary; maps_count counts them all
            "maps_count": len(self.maps_held()),
            **self.ownership.figures(),
            **self.posestate.figures(),
            **self.gate.figures(),
            **self.name_claim.figures(),  # the claim: this process's session id
            "robots_evicted": self.sweeper.evicted,
            "events_held_back": self.out.budget.held_back,  # service.live.eventbudget
        }
        if self.ros2 is not None:
            extra["ros2_robots"] = self.ros2.robots()  # robot id: namespace, the first 50
            extra["ros2_robots_count"] = self.ros2.robots_count()
            extra["ros2_scans_held"] = self.ros2.gate.held_count  # waited for odometry
            extra["ros2_scans_held_timed_out"] = self.ros2.gate.timed_out
            extra["ros2_scans_laser_at_base"] = self.ros2.laser_at_base  # no tf_static link
            extra["ros2_robots_without_odometry"] = self.ros2.robots_without_odometry()
        return encode(
            self.stats.health(len(self._poses), self.dispatcher.dropped, extra, ready=self.ready)
        )

    def maps_held(self) -> list[str]:
        """Ids of the maps loaded."""
        return self.maps.ids()

    def _on_health_query(self, query: zenoh.Query) -> None:
        with query:
            query.reply(self.keys.health(self.settings.instance), self.health(), encoding=JSON)

    def wait(self, stop: threading.Event) -> None:
        """Block until ``stop`` is set (a signal handler sets it): timed waits in a loop, so that
        the main thread runs pending signal handlers at least once a second; it also gives freed
        heap pages back to the system now and then (:mod:`service.live.memory`)."""
        trimmer = HeapTrimmer()
        while not stop.wait(1.0) and not self.stopping.is_set():  # name lost: stopping
            trimmer.maybe()
