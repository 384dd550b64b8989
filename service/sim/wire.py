"""A plan's payloads as robots put them: WIRE.md's JSON, or ROS 2's CDR on rmw_zenoh's keys.

Both encoders prepare what does not change (a JSON body per pose, a ROS message per pose) when
they are made and add the stamp as each message is sent, so that a load generator's timed loop
only stamps and puts. Both answer the same questions (:class:`RobotWire`): the key of each of a
robot's inputs, its odometry and scan at a step, its InitialPose, a Relocalize, bad input, and
the attachment a put carries.
"""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Iterator
from typing import Any, Literal, Protocol

import numpy as np

from rlutf.scan import Scan
from schemas import InitialPose, LaserScan, Map, Relocalize, encode
from service.keys import InputKind, Keys
from service.logs.mcapfile import Record
from service.sim.plan import ExtraKind, FleetPlan

#: The ROS 2 message type of each input a ROS robot puts.
ROS_TYPES = {
    "odom": "nav_msgs/msg/Odometry",
    "scan": "sensor_msgs/msg/LaserScan",
    "initialpose": "geometry_msgs/msg/PoseWithCovarianceStamped",
}
#: Ranges in the JSON are rounded to 0.1 mm, finer than real scanners report (1 mm) and
#: less than half the bytes of a float's full ``repr``.
RANGE_DECIMALS = 4


class RobotWire(Protocol):
    """The payloads of a plan's robots (robots by index, steps as in :mod:`service.sim.plan`)."""

    #: The Zenoh encoding of its puts, if any: ``application/json`` for WIRE.md's robots.
    encoding: str | None

    def key(self, robot: int, kind: InputKind) -> str:
        """Where a robot puts inputs of ``kind``."""
        ...

    def odometry(self, robot: int, step: int, stamp_ns: int) -> bytes:
        """The robot's odometry at ``step``."""
        ...

    def scan(self, robot: int, step: int, stamp_ns: int) -> bytes:
        """The robot's scan at ``step``."""
        ...

    def initial_pose(self, robot: int, stamp_ns: int) -> bytes | None:
        """The robot's InitialPose, ``None`` when the plan gives it none."""
        ...

    def extra(self, robot: int, kind: ExtraKind, stamp_ns: int) -> tuple[str, bytes]:
        """A Relocalize or bad input: the key and the payload."""
        ...

    def attachment(self, robot: int) -> bytes | None:
        """What a put of the robot carries besides its payload."""
        ...


def map_payload(plan: FleetPlan, version: int = 1) -> bytes:
    """The plan's map as a Map message (version ``version``)."""
    geometry = plan.world.to_geojson()
    return encode(
        Map.model_validate({"map_id": plan.spec.map_id, "version": version, "geometry": geometry})
    )


def laser_scan(scan: Scan, stamp_ns: int) -> LaserScan:
    """The LaserScan message of a simulated scan (NaN, no return, becomes null)."""
    return LaserScan(
        stamp_ns=stamp_ns,
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        range_min=scan.range_min,
        range_max=scan.range_max,
        ranges=[float(r) if math.isfinite(r) else None for r in scan.ranges],
    )


def _scan_body(scan: Scan) -> str:
    ranges = [round(float(r), RANGE_DECIMALS) if math.isfinite(r) else None for r in scan.ranges]
    body = {
        "angle_min": scan.angle_min,
        "angle_increment": scan.angle_increment,
        "range_min": scan.range_min,
        "range_max": scan.range_max,
        "ranges": ranges,
    }
    return json.dumps(body)[1:]


def _odometry_body(pose: np.ndarray | tuple[float, float, float]) -> str:
    return json.dumps({"x": float(pose[0]), "y": float(pose[1]), "theta": float(pose[2])})[1:]


def _stamped(body: str, stamp_ns: int) -> bytes:
    return f'{{"stamp_ns": {stamp_ns}, {body}'.encode()


class JsonWire:
    """WIRE.md's JSON robots under ``keys``.

    Args:
        plan: the fleet.
        keys: the key layout (prefix).
    """

    encoding: str | None = "application/json"  # WIRE.md: every payload is JSON, so labelled

    def __init__(self, plan: FleetPlan, keys: Keys | None = None) -> None:
        self.plan = plan
        self.keys = keys or Keys()
        self._odometry = [[_odometry_body(o) for o in r.odometry] for r in plan.robots]
        self._scans = [[_scan_body(s) for s in r.scans] for r in plan.robots]

    def key(self, robot: int, kind: InputKind) -> str:
        """See :class:`RobotWire`."""
        return self.keys.robot(self.plan.robots[robot].robot_id, kind)

    def odometry(self, robot: int, step: int, stamp_ns: int) -> bytes:
        """See :class:`RobotWire`."""
        bodies = self._odometry[robot]
        if step < len(bodies):
            return _stamped(bodies[step], stamp_ns)
        return _stamped(_odometry_body(self.plan.robots[robot].odometry_at(step)), stamp_ns)

    def scan(self, robot: int, step: int, stamp_ns: int) -> bytes:
        """See :class:`RobotWire`."""
        return _stamped(self._scans[robot][self.plan.robots[robot].index(step)], stamp_ns)

    def initial_pose(self, robot: int, stamp_ns: int) -> bytes | None:
        """See :class:`RobotWire`."""
        p = self.plan.robots[robot].initial
        if p is None:
            return None
        msg = InitialPose(
            stamp_ns=stamp_ns,
            map_id=self.plan.spec.map_id,
            x=float(p[0]),
            y=float(p[1]),
            theta=float(p[2]),
        )
        return encode(msg)

    def extra(self, robot: int, kind: ExtraKind, stamp_ns: int) -> tuple[str, bytes]:
        """See :class:`RobotWire`."""
        if kind == "relocalize":
            msg = Relocalize(stamp_ns=stamp_ns, map_id=self.plan.spec.map_id)
            return self.key(robot, "relocalize"), encode(msg)
        if kind == "malformed":  # cut short, as by a broken writer
            return self.key(robot, "scan"), _stamped('"ranges": [1.0, 2', stamp_ns)
        # well formed, but range_max is not above range_min
        body = '"angle_min": 0.0, "angle_increment": 0.1, "range_min": 5.0, "range_max": 1.0, '
        return self.key(robot, "scan"), _stamped(body + '"ranges": [2.0]}', stamp_ns)

    def attachment(self, robot: int) -> bytes | None:
        """See :class:`RobotWire`: none."""
        return None


class CdrWire:
    """ROS 2 robots as rmw_zenoh puts them: namespace ``/ROBOT``, CDR, the 33-byte attachment.

    Odometry is ``nav_msgs/Odometry`` on ``odom``, scans ``sensor_msgs/LaserScan`` on ``scan``
    (frame ``laser`` at the base), the initial pose ``PoseWithCovarianceStamped`` on
    ``initialpose``. ROS 2 has no Relocalize topic: a plan with a Relocalize schedule is refused.

    Args:
        plan: the fleet.
        domain: ``ROS_DOMAIN_ID``.
        distro: ``jazzy`` (type hashes in the keys) or ``humble`` (none).
    """

    encoding: str | None = None  # rmw_zenoh's puts carry none

    def __init__(
        self, plan: FleetPlan, domain: int = 0, distro: Literal["jazzy", "humble"] = "jazzy"
    ) -> None:
        from service.ros2 import convert

        if plan.spec.relocalize is not None:
            raise ValueError("relocalize: ROS 2 robots have no Relocalize topic; use JSON robots")
        self.plan = plan
        self.domain, self.distro = domain, distro
        self._t = convert.typestore().types
        self._convert = convert
        self._sequence = [0] * len(plan.robots)
        self._gids = [struct.pack("<QQ", i + 1, plan.spec.seed) for i in range(len(plan.robots))]
        self._odometry = [[self._odometry_msg(o) for o in r.odometry] for r in plan.robots]
        self._scans = [[self._scan_msg(s) for s in r.scans] for r in plan.robots]

    def key(self, robot: int, kind: InputKind) -> str:
        """See :class:`RobotWire`."""
        from service.ros2 import names

        if kind not in ROS_TYPES:
            raise ValueError(f"kind: ROS 2 robots put no {kind!r}")
        topic = f"/{self.plan.robots[robot].robot_id}/{kind}"
        return names.data_key(self.domain, topic, ROS_TYPES[kind], self.distro)

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, ns = divmod(stamp_ns, 1_000_000_000)
        t = self._t
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame_id
        )

    def _pose(self, p: np.ndarray | tuple[float, float, float]) -> Any:
        t = self._t
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(p[2] / 2), w=math.cos(p[2] / 2)
            ),
        )

    def _odometry_msg(self, o: np.ndarray) -> Any:
        t = self._t
        cov = np.zeros(36)
        zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return t[self._convert.ODOMETRY](
            header=self._header(0, "odom"),
            child_frame_id="base_footprint",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(o), covariance=cov),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov
            ),
        )

    def _scan_msg(self, s: Scan, range_min: float | None = None) -> Any:
        return self._t[self._convert.LASER_SCAN](
            header=self._header(0, "laser"),
            angle_min=s.angle_min,
            angle_max=s.angle_min + s.angle_increment * (len(s.ranges) - 1),
            angle_increment=s.angle_increment,
            time_increment=0.0,
            scan_time=0.1,
            range_min=s.range_min if range_min is None else range_min,
            range_max=s.range_max,
            ranges=np.asarray(s.ranges, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32),
        )

    def odometry(self, robot: int, step: int, stamp_ns: int) -> bytes:
        """See :class:`RobotWire`."""
        plan = self.plan.robots[robot]
        msg = self._odometry[robot][plan.index(step)]
        if step >= len(plan.truth):  # the way back, or a later loop: not the way out's reading
            msg.pose.pose = self._pose(plan.odometry_at(step))
        msg.header = self._header(stamp_ns, "odom")
        return self._convert.serialize(msg, self._convert.ODOMETRY)

    def scan(self, robot: int, step: int, stamp_ns: int) -> bytes:
        """See :class:`RobotWire`."""
        msg = self._scans[robot][self.plan.robots[robot].index(step)]
        msg.header = self._header(stamp_ns, "laser")
        return self._convert.serialize(msg, self._convert.LASER_SCAN)

    def initial_pose(self, robot: int, stamp_ns: int) -> bytes | None:
        """See :class:`RobotWire`."""
        p = self.plan.robots[robot].initial
        if p is None:
            return None
        t = self._t
        msg = t[self._convert.POSE_COV](
            header=self._header(stamp_ns, "map"),
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=self._pose(p), covariance=np.zeros(36)
            ),
        )
        return self._convert.serialize(msg, self._convert.POSE_COV)

    def extra(self, robot: int, kind: ExtraKind, stamp_ns: int) -> tuple[str, bytes]:
        """See :class:`RobotWire` (no Relocalize: refused when the wire was made)."""
        if kind == "malformed":  # the encapsulation header and a few bytes: cut short
            return self.key(robot, "scan"), b"\x00\x01\x00\x00\x07"
        msg = self._scan_msg(self.plan.robots[robot].scans[0], range_min=100.0)
        msg.header = self._header(stamp_ns, "laser")
        return self.key(robot, "scan"), self._convert.serialize(msg, self._convert.LASER_SCAN)

    def attachment(self, robot: int) -> bytes | None:
        """rmw_zenoh's attachment: the robot's next sequence number, the time, its GID."""
        from service.ros2 import attachment

        self._sequence[robot] += 1
        return attachment.pack(self._sequence[robot], time.time_ns(), self._gids[robot])


def fleet_records(wire: JsonWire, steps: int, t0_ns: int, step_ns: int) -> Iterator[Record]:
    """The fleet's inputs as the service's log holds them, one at a time, in log order.

    The plan's map 1 ms before ``t0_ns``, each robot's InitialPose at ``t0_ns`` (robots
    placed without one have none), then at each step ``0..steps`` each robot's odometry and
    (from step 1) its scan, stamped ``t0_ns + step * step_ns``. ``log_time`` is strictly
    increasing: 1 ms after the stamp plus 10 us per robot, the scan 1 us after its odometry. A
    plan of fewer poses than steps drives its way back and forth (:meth:`RobotPlan.index`), so
    a long log needs no more plan than a short one.
    """
    keys = wire.keys
    before = t0_ns - 1_000_000
    map_id = wire.plan.spec.map_id
    yield Record(keys.map(map_id), "rlutf.Map", map_payload(wire.plan), before, before)
    robots = range(len(wire.plan.robots))
    for k in robots:
        start = wire.initial_pose(k, t0_ns)
        if start is not None:
            key = wire.key(k, "initialpose")
            yield Record(key, "rlutf.InitialPose", start, t0_ns + 10_000 * k, t0_ns)
    for i in range(steps + 1):
        stamp = t0_ns + i * step_ns
        for k in robots:
            at = stamp + 1_000_000 + 10_000 * k
            odom = wire.odometry(k, i, stamp)
            yield Record(wire.key(k, "odom"), "rlutf.Odometry", odom, at, stamp)
            if i > 0:
                scan = wire.scan(k, i, stamp)
                yield Record(wire.key(k, "scan"), "rlutf.LaserScan", scan, at + 1_000, stamp)
