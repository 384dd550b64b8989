"""The per-fleet state machine shared by the live service and replay.

A :class:`FleetEngine` takes decoded wire messages for robots, in each robot's arrival order,
each with the time it was received, and returns what to publish: poses and events, already
encoded. It does no I/O and reads no clock, so replaying a log's inputs through it in
``log_time`` order gives the same outputs, byte for byte.

Maps are registered with the time they were received; a robot uses, for each of its inputs, the
newest version of its map received no later than that input, so the live service (maps reach
workers a moment after they are received) and replay see the same map at the same point.

An InitialPose or Relocalize waits for its map without taking the robot off the map it is
localized on (:mod:`service.relocalization`). Different robots may be handled on different
threads at once (one robot's inputs never are): the robots' states are apart, and the maps are
registered and looked up under a lock.
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
from schemas import (
    Event,
    EventCode,
    InitialPose,
    LaserScan,
    Odometry,
    Relocalize,
    encode,
)
from schemas.fastpose import encode_pose
from service.guard import Limits, Outbound, guarded, region_on, usable_scan
from service.keys import NO_RETURNS_MESSAGE, Keys
from service.maphealth import NullEvidence, ScanEvidence
from service.prepared import MapShelf, WorldSource
from service.relocalization import (
    REQUEST_WAIT_NS,
    Episode,
    EventSpec,
    Request,
    placed_during,
    searching,
    unfit,
    wire_hypotheses,
)

__all__ = ["FleetEngine", "Outbound"]

FloatArray = np.ndarray

#: An odometry reading more than this before an InitialPose or Relocalize is not the odometry at
#: it; with no reading nearer, the first one after it is, ns.
ANCHOR_GAP_NS = 1_000_000_000


@dataclass
class _Robot:
    robot_id: str
    seed: int
    map_id: str | None = None
    map_version: int = -1
    pending: Request | None = None  # an InitialPose or Relocalize waiting for its map
    episode: Episode | None = None  # the relocalization under way
    localizer: Localizer | None = None
    odom_stamps: list[int] = field(default_factory=list)
    odom_poses: list[FloatArray] = field(default_factory=list)
    anchor: FloatArray | None = None  # odometry pose at the last processed scan
    start_stamp: int = 0  # stamp of the initial pose
    last_pose: bytes | None = None
    last_status: str = ""  # of the last pose: a lost robot's next updates search wide
    fresh: bool = False  # a new localizer (seeded) whose first update searches wide
    last_event: dict[str, int] = field(default_factory=dict)


class FleetEngine:
    """Localizes many robots; one robot's inputs must come in its arrival order.

    Args:
        keys: the key layout.
        config: localizer parameters.
        event_interval_ns: least time between two events of one code for one robot.
        limits: what is accepted beyond the schema (:mod:`service.guard`).
        evidence: where scans' map health evidence is counted (default: nowhere).
    """

    def __init__(
        self,
        keys: Keys,
        config: LocalizerConfig,
        event_interval_ns: int = 1_000_000_000,
        limits: Limits | None = None,
        evidence: ScanEvidence | None = None,
    ) -> None:
        self.keys = keys
        self.config = config
        self.event_interval_ns = event_interval_ns
        self.limits = limits or Limits()
        self.evidence = evidence if evidence is not None else NullEvidence()
        self._maps = MapShelf(config)
        self._robots: dict[str, _Robot] = {}

    # ----------------------------------------------------------------------------- maps
    def register_map(self, map_id: str, version: int, world: WorldSource, received_ns: int) -> None:
        """Make a map version available to inputs received at or after ``received_ns``.

        ``world`` may be a function that builds the map: it is built (and indexed) by the first
        input that needs it, not here, so that registering a map costs nothing.
        """
        self._maps.register(map_id, version, world, received_ns)

    def _map_at(self, map_id: str, received_ns: int) -> tuple[int, World] | None:
        return self._maps.at(map_id, received_ns)

    def _map_unready(self, map_id: str | None) -> bool:
        return map_id is not None and self._maps.unready(map_id)

    def hand_over(self) -> Outbound | None:
        """Map health evidence counted since the last call (``None``: none); counted afresh."""
        handed = self.evidence.take()
        return Outbound("evidence", "", b"", 0, evidence=tuple(handed)) if handed else None

    # ----------------------------------------------------------------------------- state
    @property
    def robot_ids(self) -> list[str]:
        """Robots with any state."""
        return list(self._robots)

    def last_pose(self, robot_id: str) -> bytes | None:
        """The last PoseEstimate published for a robot, encoded."""
        r = self._robots.get(robot_id)
        return r.last_pose if r else None

    def expects_long_update(self, robot_id: str, kinds: list[str]) -> bool:
        """Whether the robot's next inputs (of these kinds) may take long to handle.

        True while it relocalizes or is lost (its updates search the map or widely), for a
        Relocalize, for an InitialPose (its map may be new to this process), and while the
        newest version of its map (or of the map its request waits for) is not built yet: the
        first update on a map builds its index. Only a hint for scheduling: it changes when
        outputs come, never what they are. Call it while none of the robot's inputs is being
        handled.
        """
        if "relocalize" in kinds or "initialpose" in kinds:
            return True
        r = self._robots.get(robot_id)
        if r is None:
            return False
        if r.pending is not None:
            return True  # applied at the next input: its first update searches wide
        if self._map_unready(r.map_id):
            return True  # the first update on a new map version builds it
        return (
            r.fresh
            or r.last_status == "lost"
            or (r.localizer is not None and r.localizer.relocalizing)
        )

    def forget(self, robot_id: str) -> None:
        """Drop everything held for a robot (evicted after it sent nothing for long)."""
        self._robots.pop(robot_id, None)

    def _robot(self, robot_id: str) -> _Robot:
        r = self._robots.get(robot_id)
        if r is None:
            r = self._robots.setdefault(robot_id, _Robot(robot_id, zlib.crc32(robot_id.encode())))
        return r

    # ----------------------------------------------------------------------------- inputs
    def handle(
        self,
        robot_id: str,
        message: LaserScan | Odometry | InitialPose | Relocalize,
        received_ns: int,
    ) -> list[Outbound]:
        """Apply one input of one robot and return what to publish.

        An input over a limit (:func:`service.guard.check_input`) changes nothing and gives an
        Event ``invalid_message``; an update that raises is undone (the robot's state is as
        before the input) and gives an Event ``internal_error``.
        """
        return guarded(self, self._robot(robot_id), message, received_ns)

    def _handle(
        self,
        robot: _Robot,
        message: LaserScan | Odometry | InitialPose | Relocalize,
        received_ns: int,
    ) -> list[Outbound]:
        if isinstance(message, Odometry):
            self._add_odometry(robot, message)
            return []
        if isinstance(message, InitialPose | Relocalize):
            return self._request(robot, message, received_ns)
        return self._scan(robot, message, received_ns)

    def _add_odometry(self, robot: _Robot, msg: Odometry) -> None:
        """Keep one odometry reading; all or nothing, so that :func:`service.guard.guarded`
        needs no snapshot of the robot for it (the common input, half of a robot's inputs)."""
        pose = np.array([msg.x, msg.y, msg.theta], dtype=np.float64)
        i = bisect.bisect_right(robot.odom_stamps, msg.stamp_ns)
        robot.odom_stamps.insert(i, msg.stamp_ns)
        try:
            robot.odom_poses.insert(i, pose)
        except BaseException:
            del robot.odom_stamps[i]
            raise
        if len(robot.odom_stamps) > 4096:  # a robot that sends odometry but no scans
            del robot.odom_stamps[:2048], robot.odom_poses[:2048]

    def _odometry_at(self, robot: _Robot, stamp_ns: int, trim: bool = True) -> FloatArray | None:
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
        if trim:
            # Keep the last reading at or before the stamp as the base of the next interpolation.
            del stamps[: i - 1], robot.odom_poses[: i - 1]
        return at

    def _request(
        self, robot: _Robot, msg: InitialPose | Relocalize, received_ns: int
    ) -> list[Outbound]:
        """Take an InitialPose or Relocalize: applied now if its map is loaded, else it waits."""
        # Not trimmed: the robot may keep tracking from older odometry while the request waits.
        anchor = self._odometry_at(robot, msg.stamp_ns, trim=False)
        stamps = robot.odom_stamps
        if anchor is not None and stamps[-1] < msg.stamp_ns - ANCHOR_GAP_NS:
            anchor = None  # all long before (a robot back after a restart): the next one is
        if isinstance(msg, InitialPose):
            pose = np.array([msg.x, msg.y, msg.theta], dtype=np.float64)
            robot.pending = Request(
                "initialpose", msg.map_id, msg.stamp_ns, received_ns, pose, None, anchor
            )
        else:
            r = msg.region
            region = None if r is None else (r.x, r.y, r.radius)
            centre = np.array([r.x, r.y, 0.0] if r is not None else [0.0, 0.0, 0.0])
            robot.pending = Request(
                "relocalize", msg.map_id, msg.stamp_ns, received_ns, centre, region, anchor
            )
        out = self._apply(robot, received_ns)
        if robot.pending is not None:
            if robot.localizer is None:
                robot.map_id = msg.map_id  # a robot with no pose yet waits for this map
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

    def _apply(self, robot: _Robot, received_ns: int) -> list[Outbound]:
        """Apply the robot's waiting request if its map is loaded at ``received_ns``."""
        req = robot.pending
        if req is None:
            return []
        key = self.keys.robot(robot.robot_id, req.kind)
        found = self._map_at(req.map_id, received_ns)
        if found is None:
            if robot.localizer is None or received_ns - req.received_ns <= REQUEST_WAIT_NS:
                return []
            robot.pending = None
            return self._event(
                robot,
                received_ns,
                "warning",
                EventCode.MAP_NOT_FOUND,
                key,
                f"{req.kind} abandoned: map {req.map_id!r} was not loaded within "
                f"{REQUEST_WAIT_NS / 1e9:g} s; the robot stays on map {robot.map_id!r}",
            )
        robot.pending = None
        version, world = found
        if req.kind == "relocalize" and robot.localizer is not None and robot.map_id == req.map_id:
            if version != robot.map_version:
                robot.localizer.set_map(world)
        else:
            robot.localizer = Localizer(world, req.pose, self.config, seed=robot.seed)
            robot.fresh = True
            if req.kind == "initialpose" or robot.anchor is None:
                robot.anchor = req.anchor
                robot.start_stamp = req.stamp_ns
        robot.map_id, robot.map_version = req.map_id, version
        if req.kind == "initialpose":
            ended, robot.episode = robot.episode, None
            return self._events(robot, received_ns, key, placed_during(ended, req))
        robot.localizer.relocalize(region_on(req.region, world))
        robot.episode = Episode(f"requested on {req.describe()}")
        return self._events(robot, received_ns, key, robot.episode.start())

    def _world_for(self, robot: _Robot, received_ns: int) -> World | None:
        """Bring the robot's localizer up to the map version current at ``received_ns``."""
        if robot.map_id is None or robot.localizer is None:
            return None
        found = self._map_at(robot.map_id, received_ns)
        if found is None:
            return None
        version, world = found
        if version != robot.map_version:
            robot.localizer.set_map(world)
        robot.map_version = version
        return world

    def _scan(self, robot: _Robot, msg: LaserScan, received_ns: int) -> list[Outbound]:
        applied = self._apply(robot, received_ns) if robot.pending is not None else []
        world = self._world_for(robot, received_ns)
        if world is None or robot.localizer is None or robot.map_id is None:
            return self._not_processed(robot, msg, received_ns, applied)
        start = robot.start_stamp
        if robot.anchor is None:
            # No odometry at the initial pose: the first reading after it is taken as the
            # robot's odometry there (a robot that starts streaming after being placed).
            i = bisect.bisect_left(robot.odom_stamps, start)
            if i < len(robot.odom_stamps) and robot.odom_stamps[i] <= msg.stamp_ns:
                robot.anchor = robot.odom_poses[i]
            elif i == len(robot.odom_stamps) and msg.stamp_ns < start - ANCHOR_GAP_NS:
                # Its scans and odometry all stamped long before the pose: the robot's clock is
                # behind the requester's, and no reading would come after the pose for as long.
                # The pose is taken as at this scan.
                start = robot.start_stamp = msg.stamp_ns
        odom = self._odometry_at(robot, msg.stamp_ns)
        if odom is None or robot.anchor is None:
            motion = np.zeros(3)
        else:
            motion = relative(robot.anchor, odom)
        if odom is not None and (robot.anchor is not None or robot.odom_stamps[-1] >= start):
            robot.anchor = odom  # a reading from before the pose anchors nothing
        # Ranges no wall of the map can be at are no return: bounded work before any search.
        scan = usable_scan(msg, robot.localizer.map, self.limits)
        result = robot.localizer.update(motion, scan)
        robot.fresh = False
        self.evidence.observe(robot.map_id, robot.map_version, world, robot.robot_id,
                              msg.stamp_ns, result)  # fmt: skip
        episode = self._follow(robot, result)
        if not math.isfinite(result.discrepancy):
            key = self.keys.robot(robot.robot_id, "scan")
            skipped = [*applied, Outbound("skipped", key, b"", msg.stamp_ns, robot.robot_id)]
            return (
                skipped
                + self._events(robot, received_ns, key, episode)
                + self._event(
                    robot,
                    received_ns,
                    "warning",
                    EventCode.LOST,
                    key,
                    NO_RETURNS_MESSAGE,
                )
            )
        pose = self._pose(robot, msg.stamp_ns, result, received_ns)
        pose_key = pose.key
        out = [*applied, pose]
        if episode:
            out += self._events(robot, received_ns, pose_key, episode)
        if result.status == "lost" and not result.hypotheses:  # ambiguous: said once above
            out += self._event(
                robot,
                received_ns,
                "warning",
                EventCode.LOST,
                pose_key,
                unfit(result, self.config.fit_distance, self.config.min_fit)
                + searching(result.relocalizing, robot.localizer.searched_region),
            )
        return out

    def _not_processed(
        self, robot: _Robot, msg: LaserScan, received_ns: int, applied: list[Outbound]
    ) -> list[Outbound]:
        """A scan the robot's state cannot take (no pose or no map yet): skipped, and why."""
        key = self.keys.robot(robot.robot_id, "scan")
        skipped = [*applied, Outbound("skipped", key, b"", msg.stamp_ns, robot.robot_id)]
        code = EventCode.MAP_NOT_FOUND
        if robot.map_id is None and robot.pending is not None:
            why = (
                f"the {robot.pending.kind} waits for map {robot.pending.map_id!r}, which is not "
                "loaded (does a storage hold it? `rlutf map list`); scan not processed"
            )
        elif robot.map_id is None:
            code = EventCode.NOT_INITIALIZED
            why = (
                "scan before an initial pose; publish an InitialPose first (`rlutf "
                f"initialpose {robot.robot_id} --map ID --pose X,Y,THETA`)"
            )
        else:
            why = f"map {robot.map_id!r} is not loaded yet; scan not processed"
        return skipped + self._event(robot, received_ns, "warning", code, key, why)

    def _follow(self, robot: _Robot, result: LocalizeResult) -> list[EventSpec]:
        """The relocalization events of a result; an automatic relocalization starts here."""
        if not result.relocalizing:
            robot.episode = None
            return []
        if robot.episode is None:
            robot.episode = Episode(
                f"lost for {self.config.relocalize_after} scans in a row; searching the map "
                f"{robot.map_id!r} for the scan"
            )
        events, ended = robot.episode.follow(result)
        if ended:
            robot.episode = None
        return events

    def _pose(
        self, robot: _Robot, stamp_ns: int, result: LocalizeResult, received_ns: int
    ) -> Outbound:
        assert robot.map_id is not None
        payload = encode_pose(
            stamp_ns,
            robot.robot_id,
            robot.map_id,
            float(result.pose[0]),
            float(result.pose[1]),
            float(result.pose[2]),
            result.status,
            float(result.discrepancy),
            int(result.iterations),
            None if result.covariance is None else result.covariance.ravel().tolist(),
            wire_hypotheses(result),
            float(result.score),
            float(result.deviation_range),
        )
        robot.last_pose = payload
        robot.last_status = result.status
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

    def _events(
        self, robot: _Robot, now_ns: int, key: str, specs: list[EventSpec]
    ) -> list[Outbound]:
        """Events that happen once per episode: never held back by the event interval."""
        out: list[Outbound] = []
        for level, code, message in specs:
            out += self._event(robot, now_ns, level, code, key, message, limited=False)
        return out

    def _event(
        self,
        robot: _Robot,
        now_ns: int,
        level: Literal["info", "warning", "error"],
        code: str,
        key: str,
        message: str,
        limited: bool = True,
    ) -> list[Outbound]:
        last = robot.last_event.get(code)
        if limited and last is not None and now_ns - last < self.event_interval_ns:
            return []
        robot.last_event[code] = now_ns
        ev = Event(stamp_ns=now_ns, level=level, code=code, key=key, message=message)
        return [
            Outbound(
                "event", self.keys.robot_events(robot.robot_id), encode(ev), now_ns, robot.robot_id
            )
        ]
