"""CDR to WIRE.md messages and back, with rosbags' type store (no CDR written by hand).

Inputs (``sensor_msgs/msg/LaserScan``, ``nav_msgs/msg/Odometry``, the ``odom`` -> base transform
of a ``tf2_msgs/msg/TFMessage``, ``geometry_msgs/msg/PoseWithCovarianceStamped`` on
``initialpose``) become the same validated :mod:`schemas` messages the JSON front door makes, so
the engine, the log and replay cannot tell them apart. Outputs are ``amcl_pose``
(``PoseWithCovarianceStamped``) and the ``map`` -> ``odom`` transform, as Nav2 AMCL publishes
them, and the pose's quality fields as a ``diagnostic_msgs/msg/DiagnosticArray``.

A range that is NaN or infinite is no return (REP 117), like ``null`` in JSON; a ``range_max`` of
+inf (no limit) is :data:`FLOAT32_MAX`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ValidationError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from schemas import InitialPose, InvalidMessage, LaserScan, Odometry, PoseEstimate, SchemaError
from schemas._issues import issues_from_errors

if TYPE_CHECKING:
    from service.maps.mapimport import OccupancyGrid

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
#: The ``range_max`` of a LaserScan whose ``range_max`` is infinite (a driver's "no limit"): the
#: largest the message's float32 holds. The wire contract's is finite; the engine bounds it by
#: the robot's map and ``limits.max_range``. Such scans were refused, every one of them.
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: Name of the DiagnosticStatus of a robot's localization.
DIAGNOSTIC_NAME = "rlutf: localization"


class CdrError(SchemaError):
    """A CDR payload that does not decode as its type, or decodes to an invalid message."""


@cache
def typestore() -> Typestore:
    """The message definitions (the types used here are the same from Humble to Rolling)."""
    return get_typestore(Stores.ROS2_JAZZY)


def deserialize(raw: bytes, msgtype: str) -> Any:
    """One CDR message as rosbags' dataclass.

    Raises:
        CdrError: the bytes are not a ``msgtype``.
    """
    try:
        return typestore().deserialize_cdr(raw, msgtype)
    except Exception as err:  # rosbags raises struct, index, unicode and value errors
        raise CdrError(f"malformed CDR for {msgtype} ({len(raw)} bytes): {err}") from err


def serialize(msg: Any, msgtype: str) -> bytes:
    """One message as CDR (little endian, with its 4-byte encapsulation header)."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header``'s stamp in ns since the epoch."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def frame(name: str) -> str:
    """A frame id without its leading slash (tf2 and AMCL compare them so)."""
    return name.lstrip("/")


def yaw(q: Any) -> float:
    """The heading of a quaternion (rotation about z).

    Raises:
        CdrError: a quaternion of length 0 or not finite (an orientation left unset is all
            zeros): it has no heading, and tf2 refuses it too; it was taken as heading 0.
    """
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    length2 = x * x + y * y + z * z + w * w
    if not 1e-12 < length2 < math.inf:  # NaN fails both
        raise CdrError(
            f"orientation: the quaternion (x {x:g}, y {y:g}, z {z:g}, w {w:g}) has no heading "
            "(length 0 or not finite; an orientation left unset is all zeros); a heading theta "
            "is x 0, y 0, z sin(theta/2), w cos(theta/2)"
        )
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _validate(model: type[Any], data: dict[str, Any]) -> Any:
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise InvalidMessage(model.__name__, issues_from_errors(err.errors())) from err


# ------------------------------------------------------------------------------- inputs
def laser_scan(
    raw: bytes,
    sensor_offset: Sequence[float] = (0.0, 0.0, 0.0),
    offset_of: Callable[[str], Sequence[float] | None] | None = None,
) -> LaserScan:
    """A ``sensor_msgs/msg/LaserScan`` as a LaserScan.

    Args:
        raw: the CDR payload.
        sensor_offset: the laser's pose in the base frame, when ``offset_of`` does not know it.
        offset_of: the pose in the base frame of a frame id (``header.frame_id``), or ``None``.

    Raises:
        SchemaError: malformed CDR, or a field the wire contract rejects.
    """
    m = deserialize(raw, LASER_SCAN)
    if offset_of is not None:
        found = offset_of(m.header.frame_id)
        if found is not None:
            sensor_offset = found
    ranges = np.asarray(m.ranges, dtype=np.float64)
    range_max = float(m.range_max)
    if range_max == math.inf:  # no upper limit: bounded by the map in the engine, as any
        range_max = FLOAT32_MAX
    values: list[float | None] = ranges.tolist()
    if not np.isfinite(ranges).all():
        for i in np.flatnonzero(~np.isfinite(ranges)).tolist():
            values[i] = None
    data = {
        "stamp_ns": stamp_ns(m.header),
        "angle_min": float(m.angle_min),
        "angle_increment": float(m.angle_increment),
        "range_min": float(m.range_min),
        "range_max": range_max,
        "ranges": values,
        "sensor_offset": dict(zip(("x", "y", "theta"), sensor_offset, strict=True)),
    }
    return _validate(LaserScan, data)  # type: ignore[no-any-return]


def odometry(raw: bytes) -> Odometry:
    """A ``nav_msgs/msg/Odometry``'s pose as an Odometry.

    Raises:
        SchemaError: malformed CDR, or a field the wire contract rejects.
    """
    return odometry_in_frames(raw)[0]


def odometry_in_frames(raw: bytes) -> tuple[Odometry, str, str]:
    """A ``nav_msgs/msg/Odometry``'s pose as an Odometry, with its ``header.frame_id`` and its
    ``child_frame_id`` (without a leading slash).

    Raises:
        SchemaError: malformed CDR, or a field the wire contract rejects.
    """
    m = deserialize(raw, ODOMETRY)
    p = m.pose.pose
    data = {
        "stamp_ns": stamp_ns(m.header),
        "x": float(p.position.x),
        "y": float(p.position.y),
        "theta": yaw(p.orientation),
    }
    out: Odometry = _validate(Odometry, data)
    return out, frame(m.header.frame_id), frame(m.child_frame_id)


def odometry_from_tf(raw: bytes, odom_frame: str, base_frame: str) -> list[Odometry]:
    """The ``odom_frame`` -> ``base_frame`` transforms of a ``tf2_msgs/msg/TFMessage``.

    Other transforms (the ``map`` -> ``odom`` we publish, the robot's links) are left out.

    Raises:
        SchemaError: malformed CDR, or a wanted transform the wire contract rejects.
    """
    return odometry_from_tf_in_frames(raw, odom_frame, base_frame)[0]


def odometry_from_tf_in_frames(
    raw: bytes, odom_frame: str, base_frame: str
) -> tuple[list[Odometry], list[tuple[str, str]]]:
    """The ``odom_frame`` -> ``base_frame`` transforms of a ``tf2_msgs/msg/TFMessage``, with
    the frames ``(parent, child)`` of each transform it carries (without a leading slash).

    Raises:
        SchemaError: malformed CDR, or a wanted transform the wire contract rejects.
    """
    m = deserialize(raw, TF_MESSAGE)
    out = []
    frames = [(frame(t.header.frame_id), frame(t.child_frame_id)) for t in m.transforms]
    for t, (parent, child) in zip(m.transforms, frames, strict=True):
        if parent != odom_frame or child != base_frame:
            continue
        tr = t.transform
        data = {
            "stamp_ns": stamp_ns(t.header),
            "x": float(tr.translation.x),
            "y": float(tr.translation.y),
            "theta": yaw(tr.rotation),
        }
        out.append(_validate(Odometry, data))
    return out, frames


def tf_frames(raw: bytes) -> list[tuple[str, str]]:
    """The frames ``(parent, child)`` of each transform of a ``tf2_msgs/msg/TFMessage``
    (without a leading slash); the transforms themselves are not read.

    Raises:
        CdrError: malformed CDR.
    """
    m = deserialize(raw, TF_MESSAGE)
    return [(frame(t.header.frame_id), frame(t.child_frame_id)) for t in m.transforms]


def static_transforms(raw: bytes) -> list[tuple[str, str, tuple[float, float, float]]]:
    """The transforms of a ``tf2_msgs/msg/TFMessage``: ``(parent, child, (x, y, yaw))``.

    Raises:
        SchemaError: malformed CDR.
    """
    m = deserialize(raw, TF_MESSAGE)
    out = []
    for t in m.transforms:
        tr = t.transform
        pose = (float(tr.translation.x), float(tr.translation.y), yaw(tr.rotation))
        out.append((frame(t.header.frame_id), frame(t.child_frame_id), pose))
    return out


def initial_pose(raw: bytes, map_id: str, global_frame: str = "map") -> InitialPose:
    """A ``geometry_msgs/msg/PoseWithCovarianceStamped`` (RViz's "2D Pose Estimate").

    As AMCL does, the pose must be in ``global_frame``.

    Raises:
        SchemaError: malformed CDR, another frame, or a field the wire contract rejects.
    """
    m = deserialize(raw, POSE_COV)
    got = frame(m.header.frame_id)
    if got != global_frame:
        raise CdrError(
            f"header.frame_id: the initial pose must be in {global_frame!r}, not {got!r}"
        )
    p = m.pose.pose
    data = {
        "stamp_ns": stamp_ns(m.header),
        "map_id": map_id,
        "x": float(p.position.x),
        "y": float(p.position.y),
        "theta": yaw(p.orientation),
    }
    return _validate(InitialPose, data)  # type: ignore[no-any-return]


def wire_json(message: BaseModel) -> bytes:
    """A converted input as the JSON the log records (pydantic's serializer).

    Not :func:`schemas.encode`: Python's float ``repr`` costs about a microsecond a number
    here, so encoding a 720-beam scan took ~0.9 ms in the service's main process, ten times the
    decode. pydantic-core writes the same fields in the same order with shortest round-trip
    floats, so the payload decodes to the same message, bit for bit (tested), and equal
    messages give equal bytes.
    """
    return message.model_dump_json().encode()


def occupancy_grid(raw: bytes) -> tuple[OccupancyGrid, int]:
    """A ``nav_msgs/msg/OccupancyGrid`` as the grid the map import takes, and its stamp.

    As map_server reads a grid: free below 25 %, occupied above 65 %, unknown (-1) neither.

    Raises:
        SchemaError: malformed CDR, or a grid whose size does not match its data.
    """
    from service.maps.mapimport import OccupancyGrid  # scikit-image: only when a map comes

    m = deserialize(raw, OCCUPANCY_GRID)
    info = m.info
    rows, cols = int(info.height), int(info.width)
    data = np.asarray(m.data, dtype=np.int8)
    if rows * cols == 0 or data.size != rows * cols:
        raise CdrError(f"info: {cols} x {rows} cells, but {data.size} values in data")
    grid = data.reshape(rows, cols)  # row 0 at the origin, the bottom, as the import wants
    o = info.origin
    try:
        out = OccupancyGrid(
            data=grid,
            free=(grid >= 0) & (grid < 25),
            occupied=grid > 65,
            resolution=float(info.resolution),
            origin=(float(o.position.x), float(o.position.y), yaw(o.orientation)),
        )
    except ValueError as err:
        raise CdrError(f"info: {err}") from err
    return out, stamp_ns(m.header)


# ------------------------------------------------------------------------------- outputs
def _header(stamp: int, frame_id: str) -> Any:
    t = typestore().types
    sec, nanosec = divmod(stamp, 1_000_000_000)
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


def _quaternion(theta: float) -> Any:
    return typestore().types["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(theta / 2.0), w=math.cos(theta / 2.0)
    )


def pose_covariance(covariance: Sequence[float] | None) -> np.ndarray:
    """The 6x6 row-major covariance (x, y, z, roll, pitch, yaw) of a 3x3 (x, y, theta) one.

    The x, y and yaw rows and columns hold the estimate's covariance; z, roll and pitch are
    zero, as AMCL leaves them.
    """
    out = np.zeros(36, dtype=np.float64)
    if covariance is not None:
        c = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        idx = (0, 1, 5)
        for i in range(3):
            for j in range(3):
                out[6 * idx[i] + idx[j]] = c[i, j]
    return out


def amcl_pose(pose: PoseEstimate, frame_id: str = "map") -> bytes:
    """A PoseEstimate as ``amcl_pose`` (PoseWithCovarianceStamped in ``frame_id``), CDR."""
    t = typestore().types
    msg = t[POSE_COV](
        header=_header(pose.stamp_ns, frame_id),
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=pose.x, y=pose.y, z=0.0),
                orientation=_quaternion(pose.theta),
            ),
            covariance=pose_covariance(pose.covariance),
        ),
    )
    return serialize(msg, POSE_COV)


def quality_diagnostics(pose: PoseEstimate) -> bytes:
    """A PoseEstimate's quality as a DiagnosticArray of one status, CDR.

    Level OK while the pose is not ``lost`` and scores at least 0.5, WARN under 0.5, ERROR when
    ``lost``; the values are VDA 5050's ``agvPosition`` fields under their WIRE.md names
    (``localization_score``, ``deviation_range``, ``position_initialized``) and the pose's
    ``status`` and ``map_id``, as strings (DiagnosticStatus carries strings).
    """
    t = typestore().types
    status = t["diagnostic_msgs/msg/DiagnosticStatus"]
    score = pose.localization_score
    # DiagnosticStatus's constants OK, WARN and ERROR
    if pose.status == "lost":
        level = 2
    elif score is not None and score < 0.5:
        level = 1
    else:
        level = 0
    pairs = {
        "localization_score": "" if score is None else repr(score),
        "deviation_range": "" if pose.deviation_range is None else repr(pose.deviation_range),
        "position_initialized": "false" if pose.status == "lost" else "true",
        "status": pose.status,
        "map_id": pose.map_id,
    }
    kv = t["diagnostic_msgs/msg/KeyValue"]
    msg = t[DIAGNOSTIC_ARRAY](
        header=_header(pose.stamp_ns, ""),
        status=[
            status(
                level=level,
                name=DIAGNOSTIC_NAME,
                message=pose.status,
                hardware_id=pose.robot_id,
                values=[kv(key=k, value=v) for k, v in pairs.items()],
            )
        ],
    )
    return serialize(msg, DIAGNOSTIC_ARRAY)


def transform(
    pose: Sequence[float] | np.ndarray, stamp: int, parent: str = "map", child: str = "odom"
) -> bytes:
    """A TFMessage holding one transform ``parent`` -> ``child`` (x, y, theta), CDR."""
    t = typestore().types
    msg = t[TF_MESSAGE](
        transforms=[
            t["geometry_msgs/msg/TransformStamped"](
                header=_header(stamp, parent),
                child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](
                        x=float(pose[0]), y=float(pose[1]), z=0.0
                    ),
                    rotation=_quaternion(float(pose[2])),
                ),
            )
        ]
    )
    return serialize(msg, TF_MESSAGE)
