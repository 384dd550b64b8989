"""The live ROS 2 front door: rmw_zenoh robots on the service's Zenoh session.

A Zenoh callback parses the key (topic, type, hash naming), maps the namespace to a robot,
decodes and validates the CDR into a WIRE.md message and hands it to the service's ``offer``
(the path JSON inputs take: ownership, recording as JSON, the robot's mailbox). Bad input (a
malformed payload, a wrong type on a topic, a namespace that is not a robot id, an initial pose
in another frame) is dropped with an Event through ``reject``; nothing else is touched. Odometry
in other frames than the settings name is taken, and said through ``warn``; so is a robot whose
tf carries its odometry under other frames, which is not found (:mod:`service.ros2.frames`), and
one whose scans come but no Odometry (:mod:`service.ros2.odomwatch`).

Each pose the engine computes for a ROS robot goes out as ``amcl_pose`` (reliable,
transient-local, depth 1: an advanced publisher with a one-sample cache and a sample-miss
heartbeat, as rmw_zenoh declares it) and as the ``map`` -> ``odom`` transform on the robot's
``tf`` (map -> base composed with the inverse of the robot's odometry at the scan's stamp,
stamped ahead by the transform tolerance), and its quality (``localization_score``,
``deviation_range``) as a DiagnosticArray on the robot's ``diagnostics``, each sample with
rmw_zenoh's attachment, on the key the robot's own distribution listens on. Liveliness tokens
announce the node and its topics, so ``ros2 node list`` and ``ros2 topic list`` show them. The
robots held, and the tokens and publishers of each, are :mod:`service.ros2.roster`'s. AMCL's
``reinitialize_global_localization`` service is served by :mod:`service.ros2.globalloc`.
Started without a map, ``rlutf serve`` says at once what will be refused, once for all its
processes (:func:`service.ros2.entities.no_map_warning`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from functools import partial
from typing import Any, Literal

import numpy as np
import zenoh
import zenoh.ext

from schemas import EventCode, PoseEstimate, SchemaError, decode
from service.config import Ros2Settings
from service.keys import InputKind, Keys, Message, printable
from service.ros2 import convert, names
from service.ros2.entities import undeclare
from service.ros2.frames import TF_ODOMETRY_WAIT_S, OdometryFrames, TfOdometryFrames
from service.ros2.gate import OdometryGate
from service.ros2.globalloc import GlobalLocalization
from service.ros2.gridmaps import GridImports
from service.ros2.odomwatch import odometry_watch
from service.ros2.roster import Limit, Publisher, Roster
from service.ros2.statictf import StaticTrees
from service.ros2.trail import map_to_odom

log = logging.getLogger(__name__)

Offer = Callable[[str, InputKind, bytes, Message, int], None]
"""Hand a validated input on: robot, kind, JSON payload, message, receive time (ns)."""
Reject = Callable[[str | None, str, str, int], None]
"""Report bad input: robot (``None`` if unknown), key, what is wrong, receive time (ns)."""
Warn = Callable[[str, str, str, str, int], None]
"""Report input that is not as the settings expect: robot, Event code, key, what, receive time
(ns)."""
Clock = Callable[[], int]

Leaf = Literal["scan", "odom", "initialpose", "tf"]


class Ros2FrontDoor:
    """ROS 2 robots in, ``amcl_pose``, ``map`` -> ``odom`` and ``diagnostics`` out.

    Args:
        settings: the ``ros2`` settings.
        offer: where validated inputs go.
        reject: where bad input is reported.
        clock: receive times (ns since the epoch, increasing).
        max_payload_bytes: largest payload accepted.
        keys: the key layout (maps from ``map_topic`` are put on its map keys).
        max_robots: most robots (namespaces) held; the inputs of one more are refused, once
            those with no input for ``idle_ns`` are dropped.
        on_limit: where such a refusal is reported (at most once a second).
        idle_ns: how long a robot may send nothing before it makes room (``robot_idle_s``).
        warn: where input not as the settings expect is reported (odometry in another frame
            than ``odom_frame``, odometry on tf not found: :mod:`service.ros2.frames`; scans
            with no odometry: :mod:`service.ros2.odomwatch`); by default the log.
    """

    def __init__(
        self,
        settings: Ros2Settings,
        offer: Offer,
        reject: Reject,
        clock: Clock,
        max_payload_bytes: int = 1_000_000,
        keys: Keys | None = None,
        max_robots: int = 10_000,
        on_limit: Limit | None = None,
        idle_ns: int = 3600 * 1_000_000_000,
        warn: Warn | None = None,
    ) -> None:
        self.settings = settings
        self.keys = keys or Keys()
        self.offer = offer
        self.reject = reject
        self.warn = warn or _log_warning
        self.clock = clock
        self.max_payload_bytes = max_payload_bytes
        self.max_robots = max_robots
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        overrides = {ns: r.robot_id for ns, r in settings.robots.items() if r.robot_id}
        self._overrides = overrides
        topics: dict[str, Leaf] = {
            settings.scan_topic: "scan",
            settings.initialpose_topic: "initialpose",
        }
        if settings.odom_source == "odom":
            topics[settings.odom_topic] = "odom"
        else:
            topics[settings.tf_topic] = "tf"
        self._topics = topics
        subscribed = [(name, _EXPECTED[leaf], _QOS[leaf]) for name, leaf in topics.items()]
        self.roster = Roster(
            settings, subscribed, max_robots, idle_ns, on_limit, self._forgotten, self._publish
        )
        # the robots' tf_static
        self.statics = StaticTrees(settings.base_frame, max_robots, self.roster.holds_namespace)
        self.frames = OdometryFrames(settings.odom_frame, settings.base_frame)
        self.tf_frames = TfOdometryFrames(
            settings.global_frame,
            settings.odom_frame,
            settings.base_frame,
            int(TF_ODOMETRY_WAIT_S * 1e9),
        )
        self.gate = OdometryGate(offer, clock, int(settings.odom_wait_s * 1e9))
        self.odometry_watch = odometry_watch(settings, clock, max_payload_bytes)
        self.grids = GridImports(settings, reject, clock, self._put_map)
        self.globalloc = GlobalLocalization(settings, self.gate.put, reject, clock, overrides)
        self._stop = threading.Event()
        self._flusher: threading.Thread | None = None

    # ------------------------------------------------------------------------- lifecycle
    def start(self, session: zenoh.Session) -> None:
        """Declare the node's token and the subscriptions."""
        s = self.settings
        self._session = session
        self.roster.start(session)
        zid = str(session.zid())
        self._declared.append(
            session.liveliness().declare_token(names.node_token(s.domain_id, zid, 0))
        )
        for name, leaf in self._topics.items():
            key = names.subscription_key(s.domain_id, name)
            self._declared.append(session.declare_subscriber(key, partial(self._on, leaf)))
        # tf_static and maps are transient local: published once, maybe long ago, so a late
        # joiner asks the publishers' caches for the last sample (as rmw_zenoh's subscribers).
        cached = ((s.tf_static_topic, self._on_static), (s.map_topic, self.grids.on_sample))
        for topic, callback in cached:
            if topic:
                self._declared.append(
                    zenoh.ext.declare_advanced_subscriber(
                        session,
                        names.subscription_key(s.domain_id, topic),
                        callback,
                        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
                    )
                )
        self.globalloc.start(session)
        self.odometry_watch.start(session)
        self._flusher = threading.Thread(target=self._flush, name="rlutf-ros2-gate", daemon=True)
        self._flusher.start()
        log.info("ROS 2 front door on domain %d: %s", s.domain_id, ", ".join(self._topics))

    def _flush(self) -> None:
        period = max(min(self.settings.odom_wait_s / 4, 0.05), 0.005)
        while not self._stop.wait(period):
            self.gate.flush()

    def close(self) -> None:
        """Undeclare publishers, tokens and subscriptions."""
        self._stop.set()
        self.grids.close()
        self.globalloc.close()
        self.odometry_watch.close()
        if self._flusher is not None:
            self._flusher.join(1.0)
        self.roster.close()
        for d in reversed(self._declared):
            undeclare(d)
        self._declared.clear()

    def robots(self, most: int = 50) -> dict[str, str]:
        """Robot id to namespace of the ROS robots held, the first ``most`` by id."""
        return self.roster.held(most)

    def robots_count(self) -> int:
        """How many ROS robots are held."""
        return self.roster.count()

    def robots_without_odometry(self) -> int:
        """How many ROS robots have been said to have no odometry, and still have none."""
        return self.odometry_watch.said() + self.tf_frames.said()

    # ------------------------------------------------------------------------- inputs
    def _on(self, leaf: Leaf, sample: zenoh.Sample) -> None:
        try:
            self._handle(str(sample.key_expr), sample.payload.to_bytes(), leaf)
        except Exception:  # a callback must never raise into zenoh
            log.exception("ROS 2 input on %s failed", printable(str(sample.key_expr)))

    def _handle(self, key: str, raw: bytes, leaf: Leaf) -> None:
        s = self.settings
        received = self.clock()
        dk = names.parse_data_key(key, s.domain_id)
        if dk is None:
            return  # not an rmw_zenoh data key (another tool's key under the domain)
        try:
            robot_id = names.robot_of_namespace(dk.namespace, s.root_robot, self._overrides)
        except names.NamespaceError as err:
            self.reject(None, key, str(err), received)
            return
        expected = _EXPECTED[leaf]
        if dk.msgtype != expected:  # before the robot is made: no tokens for a stray topic
            self.reject(
                robot_id, key, f"{dk.topic} carries {dk.msgtype}, expected {expected}", received
            )
            return
        if len(raw) > self.max_payload_bytes:
            self.reject(
                robot_id,
                key,
                f"payload too large: {len(raw)} bytes, limit {self.max_payload_bytes}",
                received,
            )
            return
        if not self.roster.room(dk.namespace, robot_id, key, received):
            return
        try:  # decoded first: input that is no message makes no robot
            messages = self._decode(dk.namespace, robot_id, raw, leaf, key, received)
        except SchemaError as err:
            self.reject(robot_id, key, str(err), received)
            return
        robot = self.roster.robot(robot_id, dk.namespace, dk.distro, received)
        for kind, msg in messages:
            if kind == "odom":
                pose = np.array([msg.x, msg.y, msg.theta])  # type: ignore[union-attr]
                self.roster.add_odometry(robot, msg.stamp_ns, pose)
                self.odometry_watch.odometry(robot_id)
            elif kind == "scan":
                warning = self.odometry_watch.scan(robot_id, dk.namespace, received)
                if warning is not None:
                    self.warn(robot_id, EventCode.ODOMETRY_NOT_FOUND, key, warning, received)
            self.gate.put(robot_id, kind, convert.wire_json(msg), msg)

    def _on_static(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        dk = names.parse_data_key(key, self.settings.domain_id)
        if dk is None:
            return
        size = len(sample.payload)
        if size > self.max_payload_bytes:  # not decoded: 10 MB took 1.7 s of the service's CPU
            why = f"payload too large: {size} bytes, limit {self.max_payload_bytes}"
            self.reject(None, key, why, self.clock())
            return
        try:
            if dk.msgtype != convert.TF_MESSAGE:
                raise convert.CdrError(f"{dk.topic} carries {dk.msgtype}, expected a TFMessage")
            found = convert.static_transforms(sample.payload.to_bytes())
        except SchemaError as err:
            self.reject(None, key, str(err), self.clock())
            return
        self.statics.add(dk.namespace, found)

    @property
    def laser_at_base(self) -> int:
        """Scans whose frame the robot's tf_static does not link to the base."""
        return self.statics.laser_at_base

    def _put_map(self, map_id: str, payload: bytes) -> None:
        session = self._session
        if session is not None:
            # Into the store and to every instance, as `rlutf map put` does.
            session.put(self.keys.map(map_id), payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    def _decode(
        self, namespace: str, robot_id: str, raw: bytes, leaf: Leaf, key: str, received: int
    ) -> list[tuple[InputKind, Message]]:
        s = self.settings
        if leaf == "scan":
            offset_of = partial(self.statics.laser_offset, namespace, robot_id)
            return [("scan", convert.laser_scan(raw, offset_of=offset_of))]
        if leaf == "odom":
            odom, frame_id, child = convert.odometry_in_frames(raw)
            if s.publish_tf:  # the frames name nothing else the service publishes
                self._check_frames(namespace, robot_id, frame_id, child, key, received)
            return [("odom", odom)]
        if leaf == "tf":
            found, frames = convert.odometry_from_tf_in_frames(raw, s.odom_frame, s.base_frame)
            warning = self.tf_frames.check(robot_id, bool(found), frames, received)
            if warning is not None:
                self.warn(robot_id, EventCode.ODOMETRY_NOT_FOUND, key, warning, received)
            return [("odom", m) for m in found]
        map_id = s.robot(namespace).map_id or s.map_id
        if map_id is None:
            raise convert.CdrError(
                "no map for ROS 2 robots: give ros2.map_id (--ros-map) or ros2.robots."
                f"{namespace.strip('/') or '/'}.map_id"
            )
        return [("initialpose", convert.initial_pose(raw, map_id, s.global_frame))]

    def _check_frames(
        self, namespace: str, robot_id: str, frame_id: str, child: str, key: str, received: int
    ) -> None:
        """Say an odometry whose frames make the ``map`` -> odom published wrong (taken all the
        same: the poses are right)."""
        offset = None
        if child != self.settings.base_frame:
            offset = self.statics.offset(namespace, child)
        warning = self.frames.check(robot_id, frame_id, child, offset)
        if warning is not None:
            self.warn(robot_id, EventCode.FRAME_MISMATCH, key, warning, received)

    def forget(self, robot_id: str) -> None:
        """Drop a robot the service evicted: its tokens, publishers and held input go (its
        next input makes it anew)."""
        self.roster.forget(robot_id)

    def _forgotten(self, robot_id: str, namespace: str) -> None:
        self.statics.forget(namespace)
        self.gate.forget(robot_id)
        self.frames.forget(robot_id)
        self.tf_frames.forget(robot_id)
        self.odometry_watch.forget(robot_id)

    # ------------------------------------------------------------------------- outputs
    def on_pose(self, robot_id: str, payload: bytes) -> None:
        """Publish a PoseEstimate of a ROS robot as ``amcl_pose`` and ``map`` -> ``odom``.

        A robot whose publishers are not declared yet has its pose published once they are.
        """
        pubs = self.roster.publishers(robot_id, payload)
        if pubs is not None:  # None: a robot of the JSON front door, or one still declared
            self._publish(robot_id, payload, pubs)

    def _publish(self, robot_id: str, payload: bytes, pubs: dict[str, Publisher]) -> None:
        try:
            pose = decode(PoseEstimate, payload, max_bytes=self.max_payload_bytes)
        except SchemaError:
            log.exception("a pose of %s does not decode", robot_id)
            return
        s = self.settings
        now = self.clock()
        self._put(pubs.get(convert.POSE_COV), convert.amcl_pose(pose, s.global_frame), now)
        if s.diagnostics_topic:
            self._put(pubs.get(convert.DIAGNOSTIC_ARRAY), convert.quality_diagnostics(pose), now)
        if not s.publish_tf:
            return
        odom = self.roster.odometry_at(robot_id, pose.stamp_ns)
        if odom is None:
            return  # no odometry yet: no map -> odom (AMCL waits for odom -> base too)
        map_odom = map_to_odom([pose.x, pose.y, pose.theta], odom)
        stamp = pose.stamp_ns + int(s.transform_tolerance_s * 1e9)
        self._put(
            pubs.get(convert.TF_MESSAGE),
            convert.transform(map_odom, stamp, s.global_frame, s.odom_frame),
            now,
        )

    @staticmethod
    def _put(pub: Publisher | None, payload: bytes, now: int) -> None:
        if pub is None:
            return
        try:
            pub.publisher.put(payload, attachment=pub.sequencer.next(now))
        except zenoh.ZError:
            log.warning("could not publish on %s", pub.key, exc_info=True)


def _log_warning(robot_id: str, code: str, key: str, message: str, received: int) -> None:
    log.warning("%s: %s (on %s)", code, message, printable(key))


_QOS: dict[Leaf, names.Qos] = {
    "scan": names.SENSOR_QOS,
    "odom": names.ODOM_QOS,
    "initialpose": names.INITIALPOSE_QOS,
    "tf": names.TF_QOS,
}
_EXPECTED: dict[Leaf, str] = {
    "scan": convert.LASER_SCAN,
    "odom": convert.ODOMETRY,
    "initialpose": convert.POSE_COV,
    "tf": convert.TF_MESSAGE,
}
