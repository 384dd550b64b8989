"""The per-fleet state machine shared by the live service and replay.

A :class:`FleetEngine` takes decoded wire messages for robots, in each robot's arrival order,
each with the time it was received, and returns what to publish: poses and events, already
encoded. It does no I/O and reads no clock, so replaying a log's inputs through it in
``log_time`` order gives the same outputs, byte for byte.

Maps are registered with the time they were received; a robot uses, for each of its inputs, the
newest version of its map received no later than that input. This makes the live service (maps
reach worker processes a moment after they are received) and replay (maps are read from the log
in order) see the same map at the same point of every robot's input.
"""

from __future__ import annotations

import bisect
import math
import zlib
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from rlutf.localizer import Localizer, LocalizerConfig, LocalizeResult
from rlutf.map import Map as World
from rlutf.motion import interpolate, relative
from rlutf.scan import Scan
from schemas import Event, EventCode, InitialPose, LaserScan, Odometry, PoseEstimate, encode
from service.keys import Keys

FloatArray = np.ndarray
OutKind = Literal["pose", "event", "need_map", "skipped"]

#: Versions of one map kept for inputs that were received before a newer version.
_MAP_VERSIONS_KEPT = 3


@dataclass(frozen=True)
class Outbound:
    """Something the engine wants published.

    Attributes:
        kind: ``pose`` (a PoseEstimate for ``key``), ``event`` (an Event for ``key``),
            ``need_map`` (``map_id`` is wanted from the store; nothing is published) or
            ``skipped`` (a scan was not turned into a pose; counted, nothing is published).
        key: the Zenoh key to put on.
        payload: encoded JSON.
        stamp_ns: the message's own stamp (MCAP ``publish_time``).
        robot: the robot concerned, if any.
        map_id: for ``need_map``.
        status: for ``pose``: the pose status.
        received_ns: for ``pose``: when the scan it answers was received.
    """

    kind: OutKind
    key: str
    payload: bytes
    stamp_ns: int
    robot: str | None = None
    map_id: str | None = None
    status: str | None = None
    received_ns: int | None = None


@dataclass
class _MapVersions:
    received: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)
    worlds: list[World] = field(default_factory=list)

    def at(self, received_ns: int) -> tuple[int, World] | None:
        i = bisect.bisect_right(self.received, received_ns) - 1
        if i < 0:
            return None
        return self.versions[i], self.worlds[i]


@dataclass
class _Robot:
    robot_id: str
    seed: int
    map_id: str | None = None
    map_version: int = -1
    start: FloatArray | None = None  # initial pose waiting for its map
    localizer: Localizer | None = None
    odom_stamps: list[int] = field(default_factory=list)
    odom_poses: list[FloatArray] = field(default_factory=list)
    anchor: FloatArray | None = None  # odometry pose at the last processed scan
    start_stamp: int = 0  # stamp of the initial pose
    last_pose: bytes | None = None
    last_event: dict[str, int] = field(default_factory=dict)


class FleetEngine:
    """Localizes many robots; one robot's inputs must come in its arrival order.

    Args:
        keys: the key layout.
        config: localizer parameters.
        event_interval_ns: least time between two events of one code for one robot.
    """

    def __init__(
        self, keys: Keys, config: LocalizerConfig, event_interval_ns: int = 1_000_000_000
    ) -> None:
        self.keys = keys
        self.config = config
        self.event_interval_ns = event_interval_ns
        self._maps: dict[str, _MapVersions] = {}
        self._robots: dict[str, _Robot] = {}

    # ----------------------------------------------------------------------------- maps
    def register_map(self, map_id: str, version: int, world: World, received_ns: int) -> None:
        """Make a map version available to inputs received at or after ``received_ns``."""
        book = self._maps.setdefault(map_id, _MapVersions())
        if book.versions and version <= book.versions[-1]:
            return
        book.received.append(received_ns)
        book.versions.append(version)
        book.worlds.append(world)
        if len(book.worlds) > _MAP_VERSIONS_KEPT:
            del book.received[0], book.versions[0], book.worlds[0]

    # ----------------------------------------------------------------------------- state
    @property
    def robot_ids(self) -> list[str]:
        """Robots with any state."""
        return list(self._robots)

    def last_pose(self, robot_id: str) -> bytes | None:
        """The last PoseEstimate published for a robot, encoded."""
        r = self._robots.get(robot_id)
        return r.last_pose if r else None

    def _robot(self, robot_id: str) -> _Robot:
        r = self._robots.get(robot_id)
        if r is None:
            r = _Robot(robot_id, zlib.crc32(robot_id.encode()))
            self._robots[robot_id] = r
        return r

    # ----------------------------------------------------------------------------- inputs
    def handle(
        self,
        robot_id: str,
        message: LaserScan | Odometry | InitialPose,
        received_ns: int,
    ) -> list[Outbound]:
        """Apply one input of one robot and return what to publish."""
        robot = self._robot(robot_id)
        if isinstance(message, Odometry):
            self._add_odometry(robot, message)
            return []
        if isinstance(message, InitialPose):
            return self._initial_pose(robot, message, received_ns)
        return self._scan(robot, message, received_ns)

    def _add_odometry(self, robot: _Robot, msg: Odometry) -> None:
        pose = np.array([msg.x, msg.y, msg.theta], dtype=np.float64)
        i = bisect.bisect_right(robot.odom_stamps, msg.stamp_ns)
        robot.odom_stamps.insert(i, msg.stamp_ns)
        robot.odom_poses.insert(i, pose)
        if len(robot.odom_stamps) > 4096:  # a robot that sends odometry but no scans
            del robot.odom_stamps[:2048], robot.odom_poses[:2048]

    def _odometry_at(self, robot: _Robot, stamp_ns: int) -> FloatArray | None:
        """Odometry pose at ``stamp_ns``: interpolated, else the latest before; never ahead."""
        stamps = robot.odom_stamps
        if not stamps:
            return None
        i = bisect.bisect_right(stamps, stamp_ns)
        if i == 0:
            return None
        before = robot.odom_poses[i - 1]
        if i < len(stamps) and stamps[i] > stamps[i - 1]:
            frac = (stamp_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
            at = interpolate(before, robot.odom_poses[i], frac) if frac > 0 else before
        else:
            at = before
        # Keep the last reading at or before the stamp as the base of the next interpolation.
        del stamps[: i - 1], robot.odom_poses[: i - 1]
        return at

    def _initial_pose(self, robot: _Robot, msg: InitialPose, received_ns: int) -> list[Outbound]:
        robot.map_id = msg.map_id
        robot.start = np.array([msg.x, msg.y, msg.theta], dtype=np.float64)
        robot.anchor = self._odometry_at(robot, msg.stamp_ns)
        robot.start_stamp = msg.stamp_ns
        robot.localizer = None
        robot.map_version = -1
        out = []
        if self._world_for(robot, received_ns) is None:
            out.append(
                Outbound(
                    "need_map",
                    self.keys.map(msg.map_id),
                    b"",
                    msg.stamp_ns,
                    robot.robot_id,
                    msg.map_id,
                )
            )
        return out

    def _world_for(self, robot: _Robot, received_ns: int) -> World | None:
        """Bring the robot's localizer up to the map version current at ``received_ns``."""
        if robot.map_id is None:
            return None
        book = self._maps.get(robot.map_id)
        found = book.at(received_ns) if book else None
        if found is None:
            return None
        version, world = found
        if robot.localizer is None and robot.start is not None:
            robot.localizer = Localizer(world, robot.start, self.config, seed=robot.seed)
            robot.start = None
        elif robot.localizer is not None and version != robot.map_version:
            robot.localizer.set_map(world)
        robot.map_version = version
        return world

    def _scan(self, robot: _Robot, msg: LaserScan, received_ns: int) -> list[Outbound]:
        key = self.keys.robot(robot.robot_id, "scan")
        skipped = [Outbound("skipped", key, b"", msg.stamp_ns, robot.robot_id)]
        if robot.map_id is None:
            return skipped + self._event(
                robot,
                received_ns,
                "warning",
                EventCode.NOT_INITIALIZED,
                key,
                "scan before an initial pose; publish an InitialPose first",
            )
        if self._world_for(robot, received_ns) is None or robot.localizer is None:
            return skipped + self._event(
                robot,
                received_ns,
                "warning",
                EventCode.MAP_NOT_FOUND,
                key,
                f"map {robot.map_id!r} is not loaded yet; scan not processed",
            )
        if robot.anchor is None:
            # No odometry at the initial pose: the first reading after it is taken as the
            # robot's odometry there (a robot that starts streaming after being placed).
            i = bisect.bisect_left(robot.odom_stamps, robot.start_stamp)
            if i < len(robot.odom_stamps) and robot.odom_stamps[i] <= msg.stamp_ns:
                robot.anchor = robot.odom_poses[i]
        odom = self._odometry_at(robot, msg.stamp_ns)
        if odom is None or robot.anchor is None:
            motion = np.zeros(3)
        else:
            motion = relative(robot.anchor, odom)
        if odom is not None:
            robot.anchor = odom
        scan = Scan.create(
            np.array(msg.ranges, dtype=np.float64),  # None (no return) becomes NaN
            msg.angle_min,
            msg.angle_increment,
            msg.range_min,
            msg.range_max,
            (msg.sensor_offset.x, msg.sensor_offset.y, msg.sensor_offset.theta),
        )
        result = robot.localizer.update(motion, scan)
        if not math.isfinite(result.discrepancy):
            return skipped + self._event(
                robot,
                received_ns,
                "warning",
                EventCode.LOST,
                key,
                "scan has too few returns to compare; pose kept by odometry",
            )
        out = [self._pose(robot, msg.stamp_ns, result, received_ns)]
        if result.status == "lost":
            out += self._event(
                robot,
                received_ns,
                "warning",
                EventCode.LOST,
                self.keys.pose(robot.robot_id),
                f"the scan does not fit the map: {100 * result.fit:.0f} % of its returns within "
                f"{self.config.fit_distance:g} m of the map at the best pose (at least "
                f"{100 * self.config.min_fit:.0f} % needed); searching wider at the next scan",
            )
        return out

    def _pose(
        self, robot: _Robot, stamp_ns: int, result: LocalizeResult, received_ns: int
    ) -> Outbound:
        assert robot.map_id is not None
        msg = PoseEstimate(
            stamp_ns=stamp_ns,
            robot_id=robot.robot_id,
            map_id=robot.map_id,
            x=float(result.pose[0]),
            y=float(result.pose[1]),
            theta=float(result.pose[2]),
            status=result.status,
            discrepancy=float(result.discrepancy),
            iterations=int(result.iterations),
            covariance=None
            if result.covariance is None
            else tuple(float(v) for v in result.covariance.ravel()),
        )
        payload = encode(msg)
        robot.last_pose = payload
        return Outbound(
            "pose",
            self.keys.pose(robot.robot_id),
            payload,
            stamp_ns,
            robot.robot_id,
            robot.map_id,
            result.status,
            received_ns,
        )

    def _event(
        self,
        robot: _Robot,
        now_ns: int,
        level: Literal["info", "warning", "error"],
        code: str,
        key: str,
        message: str,
    ) -> list[Outbound]:
        last = robot.last_event.get(code)
        if last is not None and now_ns - last < self.event_interval_ns:
            return []
        robot.last_event[code] = now_ns
        ev = Event(stamp_ns=now_ns, level=level, code=code, key=key, message=message)
        return [
            Outbound(
                "event", self.keys.robot_events(robot.robot_id), encode(ev), now_ns, robot.robot_id
            )
        ]
