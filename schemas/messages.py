"""Pydantic models of the wire messages in WIRE.md.

Times are integer nanoseconds since the Unix epoch, lengths metres, angles radians
(counter-clockwise positive, x forward, y left; REP 103). Every model is frozen, ignores
unknown fields and rejects missing required fields, wrong types and non-finite numbers.
Sequences are stored as tuples; Python callers may pass lists.
"""

from __future__ import annotations

from typing import Annotated, Final, Literal

from pydantic import AfterValidator, Field, JsonValue, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError

from schemas._types import (
    FiniteFloat,
    Identifier,
    NonEmptyStr,
    NonNegativeFloat,
    NonNegativeInt,
    NumberOrNull,
    PositiveFloat,
    StampNs,
    Text,
    UnitFloat,
    WireModel,
    check_finite_json,
)
from schemas.geometry import Geometry

MAX_BEAMS: Final = 8192
"""Most beams accepted in one LaserScan (a 0.05 degree scanner over a full turn is 7200)."""

PoseStatus = Literal["tracking", "corrected", "lost"]
EventLevel = Literal["debug", "info", "warning", "error"]


class SensorOffset(WireModel):
    """Pose of the laser sensor in the robot's base frame."""

    x: FiniteFloat = Field(default=0.0, description="Forward offset, metres.")
    y: FiniteFloat = Field(default=0.0, description="Leftward offset, metres.")
    theta: FiniteFloat = Field(default=0.0, description="Mounting yaw, radians, counter-clockwise.")


class LaserScan(WireModel):
    """One 2D laser scan, with the meaning of ROS sensor_msgs/LaserScan.

    Beam i points at angle_min + i * angle_increment in the sensor frame. A range that is null,
    below range_min or above range_max is no return.
    """

    stamp_ns: StampNs = Field(description="Acquisition time, ns since the Unix epoch.")
    angle_min: FiniteFloat = Field(description="Angle of beam 0, radians.")
    angle_increment: FiniteFloat = Field(
        description="Angle between consecutive beams, radians; non-zero, negative if clockwise."
    )
    range_min: NonNegativeFloat = Field(description="Shortest valid range, metres.")
    range_max: FiniteFloat = Field(description="Longest valid range, metres; > range_min.")
    ranges: Annotated[tuple[NumberOrNull, ...], Field(min_length=1, max_length=MAX_BEAMS)] = Field(
        description="Range of each beam, metres; null is no return."
    )
    sensor_offset: SensorOffset = Field(
        default=SensorOffset(),  # frozen, so one shared default is safe
        description="Sensor pose in the robot's base frame; zero if absent.",
    )

    @field_validator("angle_increment")
    @classmethod
    def _nonzero_increment(cls, value: float) -> float:
        if value == 0.0:
            raise PydanticCustomError("nonzero", "angle_increment must not be 0")
        return value

    @field_validator("range_max")
    @classmethod
    def _max_above_min(cls, value: float, info: ValidationInfo) -> float:
        range_min = info.data.get("range_min")
        if range_min is not None and not value > range_min:
            raise PydanticCustomError(
                "greater_than_range_min",
                "range_max must be greater than range_min ({range_min})",
                {"range_min": range_min},
            )
        return value


class Odometry(WireModel):
    """The robot base's dead-reckoned pose in its own odometry frame.

    Only the motion between two messages is used, so the frame's origin is irrelevant.
    """

    stamp_ns: StampNs = Field(description="Time of the pose, ns since the Unix epoch.")
    x: FiniteFloat = Field(description="Position x, metres.")
    y: FiniteFloat = Field(description="Position y, metres.")
    theta: FiniteFloat = Field(description="Heading, radians.")


class InitialPose(WireModel):
    """A known pose of the robot base in map map_id; also re-seeds a lost robot."""

    stamp_ns: StampNs = Field(description="Time the pose holds, ns since the Unix epoch.")
    map_id: Identifier = Field(description="Map the pose is in.")
    x: FiniteFloat = Field(description="Position x in the map, metres.")
    y: FiniteFloat = Field(description="Position y in the map, metres.")
    theta: FiniteFloat = Field(description="Heading in the map, radians.")


class Region(WireModel):
    """A circle in map coordinates: where a robot to relocalize is known to be."""

    x: FiniteFloat = Field(description="Centre x in the map, metres.")
    y: FiniteFloat = Field(description="Centre y in the map, metres.")
    radius: PositiveFloat = Field(description="Radius, metres; > 0.")


class Relocalize(WireModel):
    """The robot is somewhere on map map_id (inside region when given): find it from its scans.

    WIRE.md v1.1. The service forgets the robot's pose and localizes it globally from its next
    scans and the odometry between them, then tracks it as usual.
    """

    stamp_ns: StampNs = Field(description="Time of the request, ns since the Unix epoch.")
    map_id: Identifier = Field(description="Map the robot is on.")
    region: Region | None = Field(
        default=None, description="Optional circle in map coordinates the robot is inside."
    )


class Hypothesis(WireModel):
    """One candidate pose of a robot being relocalized."""

    x: FiniteFloat = Field(description="Position x in the map, metres.")
    y: FiniteFloat = Field(description="Position y in the map, metres.")
    theta: FiniteFloat = Field(description="Heading in the map, radians.")
    score: UnitFloat = Field(description="How well the scans fit at this pose, 0 to 1.")


Covariance = Annotated[tuple[FiniteFloat, ...], Field(min_length=9, max_length=9)]
"""A 3x3 covariance of (x, y, theta), row-major."""


class PoseEstimate(WireModel):
    """The corrected pose of a robot, published once per processed scan."""

    stamp_ns: StampNs = Field(description="Stamp of the scan this pose is for.")
    robot_id: Identifier = Field(description="The robot.")
    map_id: Identifier = Field(description="The map the pose is in.")
    x: FiniteFloat = Field(description="Position x in the map, metres.")
    y: FiniteFloat = Field(description="Position y in the map, metres.")
    theta: FiniteFloat = Field(description="Heading in the map, radians.")
    status: PoseStatus = Field(
        description="tracking: accepted without search; corrected: the search moved the pose; "
        "lost: the scan does not fit the map at the best pose (the best one is still given)."
    )
    discrepancy: NonNegativeFloat = Field(
        description="Turning-function difference at the returned pose."
    )
    iterations: NonNegativeInt = Field(description="Search rounds used.")
    covariance: Covariance | None = Field(
        default=None,
        description="Optional 3x3 covariance of x, y, theta, row-major (9 numbers): m^2, m rad, "
        "rad^2.",
    )
    hypotheses: tuple[Hypothesis, ...] | None = Field(
        default=None,
        description="While a robot is being relocalized (v1.1): the distinct candidate poses, "
        "best first; absent otherwise.",
    )
    localization_score: UnitFloat | None = Field(
        default=None,
        description="v1.2, VDA 5050's agvPosition.localizationScore: 1 when the scan fits the map "
        "as well as this robot's scans usually do at a well-determined pose, 0 when the pose is "
        "unknown; under 0.5 when status is lost.",
    )
    deviation_range: NonNegativeFloat | None = Field(
        default=None,
        description="v1.2, VDA 5050's agvPosition.deviationRange: the radius around x, y that "
        "holds the true position with 95 % probability, metres.",
    )


class Map(WireModel):
    """A polygon map: free space is the interior, walls the boundary, holes obstacles."""

    map_id: Identifier = Field(description="The map's id, as in its key.")
    version: NonNegativeInt = Field(description="A newer version replaces an older one.")
    frame_id: NonEmptyStr = Field(default="map", description="Frame of the coordinates.")
    geometry: Geometry = Field(description="GeoJSON Polygon or MultiPolygon, metres.")


class EventCode:
    """Known values of :attr:`Event.code`; the field is a plain string, so more may appear.

    WIRE.md requires the first six; the rest are this implementation's additions.
    """

    INVALID_MESSAGE: Final = "invalid_message"
    """A payload was rejected: malformed, wrong types, missing fields or too large."""
    INVALID_KEY: Final = "invalid_key"
    """A key with a robot id or map id that does not match the id pattern, a key with extra
    levels or an unknown leaf, a DELETE on a robot key, a put on a key nothing reads."""
    MAP_NOT_FOUND: Final = "map_not_found"
    """An InitialPose or Relocalize names a map no storage answers for."""
    INVALID_MAP: Final = "invalid_map"
    """A map failed validation (schema or geometry)."""
    NOT_INITIALIZED: Final = "not_initialized"
    """A scan for a robot with no initial pose."""
    LOST: Final = "lost"
    """The localizer found no pose under its acceptance threshold."""
    SCAN_DROPPED: Final = "scan_dropped"
    """A newer scan replaced an unprocessed older one."""
    MAP_DROPPED: Final = "map_dropped"
    """A map put was not taken: too many map puts already waited to be checked or stored (a
    flood). The service then loads what the store holds; the message says what happened."""
    RECORDER_OVERFLOW: Final = "recorder_overflow"
    """The MCAP recorder's queue was full and messages were not logged."""
    RECORDING_FAILED: Final = "recording_failed"
    """The MCAP recorder could not write (a full disk, a folder gone): messages are not logged
    until it can; it tries again every few seconds."""
    RECORDING_RESUMED: Final = "recording_resumed"
    """The MCAP recorder writes again after ``recording_failed``; stamped when the gap began,
    the message says how long it could not write and how many messages were not logged
    meanwhile (also in the log, where replay audits the poses before the gap only)."""
    MAP_UPDATED: Final = "map_updated"
    """A newer map version replaced the one robots were localized on."""
    MAP_UNCHANGED: Final = "map_unchanged"
    """A map put of the very version a service holds, with the same content: nothing changed
    (the tools that put maps wait for each running service's word on a put)."""
    MAP_UNCONFIRMED: Final = "map_unconfirmed"
    """A map put not loaded because the store did not say it holds it in time (it had many big
    puts to store first): the service loads what the store holds once they are stored."""
    RELOCALIZING: Final = "relocalizing"
    """A global relocalization of a robot started (on request or by itself when lost)."""
    RELOCALIZED: Final = "relocalized"
    """A relocalization ended: one hypothesis won clearly and the robot is tracked again."""
    AMBIGUOUS: Final = "ambiguous"
    """A relocalization found several near-equal hypotheses; it follows them until one wins."""
    STATE_UNREADABLE: Final = "state_unreadable"
    """The durable pose state could not be read or its folder made; started without it."""
    STATE_WRITE_FAILED: Final = "state_write_failed"
    """The durable pose state could not be written (a full or read-only disk, its folder
    gone): a restart may not resume the robots until it can; it tries at each interval."""
    STATE_WRITE_RESUMED: Final = "state_write_resumed"
    """The durable pose state is written again after ``state_write_failed``."""
    MAP_WRITE_FAILED: Final = "map_write_failed"
    """The embedded store took a map put (it serves it, and the services load it, as any put)
    but could not write it to disk (a full or read-only disk, its folder gone): it holds it in
    memory and tries again every few seconds; a restart before then loses it."""
    MAP_WRITE_RESUMED: Final = "map_write_resumed"
    """A map held in memory after ``map_write_failed`` is written to disk."""
    STORE_IN_USE: Final = "store_in_use"
    """The embedded store's folder was replaced under it (removed and made again, a copy put in
    its place) and another running process claimed it meanwhile: both serve it; stop one."""
    MAP_VERSION_CONFLICT: Final = "map_version_conflict"
    """A map put of a version lower than the one held, or of the same version with other
    content (WIRE.md v1.2): it changed nothing; the message names both versions."""
    WORKER_LOST: Final = "worker_lost"
    """A worker process died; a new one starts and its robots are re-seeded from their poses."""
    ROBOT_EVICTED: Final = "robot_evicted"
    """A robot sent nothing for ``robot_idle_s``: its state was dropped (it starts anew)."""
    ROBOT_LIMIT: Final = "robot_limit"
    """An input for a new robot id was refused: the instance holds ``max_robots`` already."""
    STAMP_REJECTED: Final = "stamp_rejected"
    """A message's stamp is too far ahead of the service's clock to be trusted."""
    MAP_DELETED: Final = "map_deleted"
    """A DELETE on a map key: the store drops the map; robots on it keep their copy."""
    FRAME_MISMATCH: Final = "frame_mismatch"
    """A ROS 2 robot's input was taken, but its frames are not the ones the settings name (an
    Odometry in another frame than ``ros2.odom_frame``): the poses are right, a transform the
    service publishes for it is not; said once, and again when its frames change."""
    ODOMETRY_NOT_FOUND: Final = "odometry_not_found"
    """A ROS 2 robot has no odometry where the settings read it, and no ``map`` -> odom is
    published for it: read from tf (``ros2.odom_source = "tf"``), it sends tf but for seconds no
    transform from ``ros2.odom_frame`` to ``ros2.base_frame`` (the message names the frames
    seen); read as ``nav_msgs/Odometry`` (``"odom"``), its scans come for seconds with none on
    ``ros2.odom_topic`` (the message names the topic, and says to read tf when its tf carries the
    odometry). Said once, and again when other frames are seen."""
    INSTANCE_NAME_TAKEN: Final = "instance_name_taken"
    """Another running instance has this instance's name and claimed it first (two of one name
    started together, or met when a network partition healed): this instance stops (exit 1);
    the message says what it did meanwhile and how to name it."""
    INTERNAL_ERROR: Final = "internal_error"
    """An input's update failed inside the service (a bug); it was not applied, and the robot's
    state is as before it."""


KNOWN_EVENT_CODES: Final = frozenset(
    value for name, value in vars(EventCode).items() if name.isupper() and isinstance(value, str)
)
"""Every code in :class:`EventCode`."""


class Event(WireModel):
    """A problem with a robot's input or state, or with the service."""

    stamp_ns: StampNs = Field(description="When it happened, ns since the Unix epoch.")
    level: EventLevel = Field(description="Severity.")
    code: NonEmptyStr = Field(
        description="What happened, machine-readable: invalid_message, invalid_key, "
        "map_not_found, invalid_map, not_initialized, lost, scan_dropped, recorder_overflow, "
        "map_updated, relocalizing, relocalized, ambiguous, map_version_conflict; more may be "
        "added."
    )
    key: Text = Field(
        default="", description="The key involved, e.g. where a bad message came from."
    )
    message: Text = Field(
        default="", description="Human-readable explanation naming field and value."
    )


class LatencyPercentiles(WireModel):
    """Distribution of update latency, milliseconds, over recent updates."""

    p50: NonNegativeFloat = Field(default=0.0, description="Median.")
    p90: NonNegativeFloat = Field(default=0.0, description="90th percentile.")
    p99: NonNegativeFloat = Field(default=0.0, description="99th percentile.")
    max: NonNegativeFloat = Field(default=0.0, description="Largest.")
    count: NonNegativeInt = Field(default=0, description="Updates the figures are over; 0 if none.")


FreeForm = Annotated[dict[str, JsonValue], AfterValidator(check_finite_json)]


class Health(WireModel):
    """Counters and state of one service instance."""

    instance: NonEmptyStr = Field(description="Name of the instance.")
    stamp_ns: StampNs | None = Field(
        default=None, description="When the figures were taken, ns since the Unix epoch."
    )
    uptime_s: NonNegativeFloat = Field(
        default=0.0, description="Seconds since the instance started."
    )
    robots: NonNegativeInt = Field(default=0, description="Robots the instance holds.")
    received: NonNegativeInt = Field(default=0, description="Messages received.")
    rejected: NonNegativeInt = Field(default=0, description="Messages rejected as invalid.")
    processed: NonNegativeInt = Field(default=0, description="Scans processed into a pose.")
    dropped: NonNegativeInt = Field(
        default=0, description="Scans replaced by a newer one unprocessed."
    )
    latency_ms: LatencyPercentiles = Field(
        default=LatencyPercentiles(), description="Per-update latency, milliseconds."
    )
    ready: bool | None = Field(
        default=None,
        description=(
            "v1.2: true once every process of the instance can localize (kernels compiled or "
            "loaded); the instance declares its liveliness token only then."
        ),
    )
    extra: FreeForm = Field(
        default_factory=dict, description="Further implementation-defined figures."
    )
