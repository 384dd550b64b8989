"""A ROS 2 robot as rmw_zenoh puts it on the wire, written for the tests from the key format.

It uses rosbags for CDR and builds keys and attachments itself (``struct``), not with the
service's :mod:`service.ros2` helpers, so a mistake there cannot hide in both.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

from rlutf.map import Map as World
from rlutf.motion import compose
from rlutf.sim import LidarModel, simulate_scan

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
DDS = {
    "sensor_msgs/msg/LaserScan": "sensor_msgs::msg::dds_::LaserScan_",
    "nav_msgs/msg/Odometry": "nav_msgs::msg::dds_::Odometry_",
    "geometry_msgs/msg/PoseWithCovarianceStamped": (
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
    ),
    "tf2_msgs/msg/TFMessage": "tf2_msgs::msg::dds_::TFMessage_",
    "std_msgs/msg/String": "std_msgs::msg::dds_::String_",
    "diagnostic_msgs/msg/DiagnosticArray": "diagnostic_msgs::msg::dds_::DiagnosticArray_",
}


def key(domain: int, topic: str, msgtype: str, humble: bool) -> str:
    hash_ = "TypeHashNotSupported" if humble else TS.hash_rihs01(msgtype)
    return f"{domain}/{topic.strip('/')}/{DDS[msgtype]}/{hash_}"


def header(stamp_ns: int, frame_id: str) -> Any:
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def quat(theta: float) -> Any:
    return T["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2)
    )


def yaw(q: Any) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def scan_msg(
    world: World,
    pose: np.ndarray,
    stamp_ns: int,
    rng: np.random.Generator,
    frame_id: str = "base_footprint",
) -> Any:
    """A scan from ``pose`` (the laser's pose in the map), in frame ``frame_id``."""
    s = simulate_scan(world, pose, LidarModel(beams=180), rng)
    return T["sensor_msgs/msg/LaserScan"](
        header=header(stamp_ns, frame_id),
        angle_min=s.angle_min,
        angle_max=s.angle_min + s.angle_increment * (len(s.ranges) - 1),
        angle_increment=s.angle_increment,
        time_increment=0.0,
        scan_time=0.1,
        range_min=s.range_min,
        range_max=s.range_max,
        ranges=np.asarray(s.ranges, dtype=np.float32),  # NaN: no return (REP 117)
        intensities=np.zeros(0, dtype=np.float32),
    )


def odom_msg(
    pose: np.ndarray, stamp_ns: int, frame_id: str = "odom", child: str = "base_footprint"
) -> Any:
    cov = np.zeros(36)
    twist = T["geometry_msgs/msg/Twist"](
        linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return T["nav_msgs/msg/Odometry"](
        header=header(stamp_ns, frame_id),
        child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=pose[0], y=pose[1], z=0.0),
                orientation=quat(pose[2]),
            ),
            covariance=cov,
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov),
    )


def tf_msg(pose: np.ndarray, stamp_ns: int, parent: str, child: str) -> Any:
    return T["tf2_msgs/msg/TFMessage"](
        transforms=[
            T["geometry_msgs/msg/TransformStamped"](
                header=header(stamp_ns, parent),
                child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=pose[0], y=pose[1], z=0.0),
                    rotation=quat(pose[2]),
                ),
            )
        ]
    )


def initialpose_msg(pose: np.ndarray, stamp_ns: int, frame_id: str = "map") -> Any:
    cov = np.zeros(36)
    cov[0] = cov[7] = 0.25
    cov[35] = (math.pi / 12) ** 2
    return T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=header(stamp_ns, frame_id),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=pose[0], y=pose[1], z=0.0),
                orientation=quat(pose[2]),
            ),
            covariance=cov,
        ),
    )


@dataclass(eq=False)
class RosRobot:
    """A namespaced robot: truth in the map, odometry in a frame offset by ``odom_origin``."""

    namespace: str
    world: World
    truth: np.ndarray
    session: zenoh.Session
    humble: bool
    odom_origin: np.ndarray  # pose of the odom frame in the map
    t0: int = field(default_factory=time.time_ns)
    domain: int = 0
    odom_tf: bool = False
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    laser: np.ndarray | None = None  # the laser's pose in base_footprint, via base_link
    frames: tuple[str, str] = ("odom", "base_footprint")  # its odometry's frame and child
    step: int = 0
    seq: int = 0
    gid: bytes = b"\x07" * 16

    def stamp(self, i: int) -> int:
        return self.t0 + i * 100_000_000

    def odom_pose(self, i: int) -> np.ndarray:
        # odom -> base = (map -> odom)^-1 * map -> base
        o = self.odom_origin
        c, s = math.cos(o[2]), math.sin(o[2])
        d = self.truth[i, :2] - o[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], self.truth[i, 2] - o[2]])

    def put(self, name: str, msgtype: str, msg: Any, msgtype_key: str | None = None) -> None:
        raw = bytes(TS.serialize_cdr(msg, msgtype))
        self.put_raw(name, msgtype_key or msgtype, raw)

    def put_raw(self, name: str, msgtype: str, raw: bytes) -> None:
        self.seq += 1
        att = struct.pack("<qqB", self.seq, time.time_ns(), 16) + self.gid
        k = key(self.domain, f"{self.namespace}/{name}", msgtype, self.humble)
        self.session.put(k, raw, attachment=att)

    def odom(self, i: int) -> None:
        p = self.odom_pose(i)
        if self.odom_tf:
            msg = tf_msg(p, self.stamp(i), *self.frames)
            self.put("tf", "tf2_msgs/msg/TFMessage", msg)
        else:
            self.put("odom", "nav_msgs/msg/Odometry", odom_msg(p, self.stamp(i), *self.frames))

    def initial_pose(self) -> None:
        self.odom(0)
        msg = initialpose_msg(self.truth[0], self.stamp(0))
        self.put("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped", msg)

    def tf_static(self) -> None:
        """base_footprint -> base_link (10 cm up: dropped) -> laser, as a URDF gives them."""
        assert self.laser is not None
        a = tf_msg(np.zeros(3), self.stamp(0), "base_footprint", "base_link")
        b = tf_msg(self.laser, self.stamp(0), "base_link", "laser")
        msg = T["tf2_msgs/msg/TFMessage"](transforms=[*a.transforms, *b.transforms])
        self.put("tf_static", "tf2_msgs/msg/TFMessage", msg)

    def advance(self) -> int:
        self.step += 1
        self.odom(self.step)
        pose, frame = self.truth[self.step], "base_footprint"
        if self.laser is not None:
            pose, frame = compose(pose, self.laser), "laser"
        msg = scan_msg(self.world, pose, self.stamp(self.step), self.rng, frame)
        self.put("scan", "sensor_msgs/msg/LaserScan", msg)
        return self.step


@dataclass
class RosListener:
    """Collects raw samples (payload, attachment) per key."""

    samples: dict[str, list[tuple[bytes, bytes | None]]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: zenoh.Sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.lock:
            self.samples.setdefault(str(sample.key_expr), []).append(
                (sample.payload.to_bytes(), att)
            )

    def on(self, k: str) -> list[tuple[bytes, bytes | None]]:
        with self.lock:
            return list(self.samples.get(k, []))


def drive(
    robots: Sequence[RosRobot],
    steps: int,
    pause: float = 0.05,
    until: Callable[[], object] = lambda: False,
) -> None:
    """Each robot's next odometry and scan, ``steps`` times ``pause`` apart, or until
    ``until()``."""
    for _ in range(steps):
        for r in robots:
            r.advance()
        time.sleep(pause)
        if until():
            return


def others_transforms(listener: RosListener, robot: RosRobot, k: str) -> list[tuple[str, str]]:
    """The frames ``(parent, child)`` of the transforms on ``k`` that ``robot`` did not publish
    (the service's ``map`` -> ``odom``)."""
    return [pose_of_tf(raw)[1:3] for raw, att in listener.on(k) if att and att[17:] != robot.gid]


def pose_of_tf(raw: bytes) -> tuple[int, str, str, np.ndarray]:
    m = TS.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage").transforms[0]
    t = m.transform
    stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
    pose = np.array([t.translation.x, t.translation.y, yaw(t.rotation)])
    return stamp, m.header.frame_id, m.child_frame_id, pose


def map_base(map_odom: np.ndarray, odom_base: np.ndarray) -> np.ndarray:
    return compose(map_odom, odom_base)
