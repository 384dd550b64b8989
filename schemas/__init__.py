"""Wire schemas of the RLuTF localization service (WIRE.md, v1.1).

Pydantic models of every message, their validation, JSON encode/decode and JSON Schema
documents. Typical use at a boundary::

    from schemas import LaserScan, SchemaError, decode, encode

    try:
        scan = decode(LaserScan, payload)
    except SchemaError as err:  # str(err) names the field and value: "ranges[17]: ..."
        ...
    publish(encode(pose))
"""

from schemas._types import (
    ID_PATTERN,
    MAX_STAMP_NS,
    WireModel,
    valid_id,
)
from schemas.answers import (
    RobotsAnswer,
    RobotState,
    StoredVersion,
    WaitingRobot,
    encode_answer,
)
from schemas.codec import DEFAULT_MAX_BYTES, Payload, decode, encode, to_jsonable
from schemas.errors import (
    EncodeError,
    FieldIssue,
    InvalidMessage,
    InvalidUtf8,
    MalformedJson,
    PayloadTooLarge,
    SchemaError,
)
from schemas.geometry import Geometry, MultiPolygon, Polygon, Position
from schemas.maphealth import LineString, MapChange, MapHealth, MultiLineString
from schemas.messages import (
    KNOWN_EVENT_CODES,
    MAX_BEAMS,
    Event,
    EventCode,
    EventLevel,
    Health,
    Hypothesis,
    InitialPose,
    LaserScan,
    LatencyPercentiles,
    Map,
    Odometry,
    PoseEstimate,
    PoseStatus,
    Region,
    Relocalize,
    SensorOffset,
)
from schemas.names import MODELS_BY_SCHEMA_NAME, SCHEMA_NAMES, json_schema, schema_name

__all__ = [
    "DEFAULT_MAX_BYTES",
    "ID_PATTERN",
    "KNOWN_EVENT_CODES",
    "MAX_BEAMS",
    "MAX_STAMP_NS",
    "MODELS_BY_SCHEMA_NAME",
    "SCHEMA_NAMES",
    "EncodeError",
    "Event",
    "EventCode",
    "EventLevel",
    "FieldIssue",
    "Geometry",
    "Health",
    "Hypothesis",
    "InitialPose",
    "InvalidMessage",
    "InvalidUtf8",
    "LaserScan",
    "LatencyPercentiles",
    "LineString",
    "MalformedJson",
    "Map",
    "MapChange",
    "MapHealth",
    "MultiLineString",
    "MultiPolygon",
    "Odometry",
    "Payload",
    "PayloadTooLarge",
    "Polygon",
    "PoseEstimate",
    "PoseStatus",
    "Position",
    "Region",
    "Relocalize",
    "RobotState",
    "RobotsAnswer",
    "SchemaError",
    "SensorOffset",
    "StoredVersion",
    "WaitingRobot",
    "WireModel",
    "decode",
    "encode",
    "encode_answer",
    "json_schema",
    "schema_name",
    "to_jsonable",
    "valid_id",
]
