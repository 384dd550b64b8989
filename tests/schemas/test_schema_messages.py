"""The message models: WIRE.md's examples, defaults, constraints and identifiers."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from schemas import (
    ID_PATTERN,
    KNOWN_EVENT_CODES,
    MAX_BEAMS,
    Event,
    EventCode,
    Health,
    InitialPose,
    LaserScan,
    Map,
    MultiPolygon,
    Odometry,
    Polygon,
    PoseEstimate,
    SensorOffset,
    decode,
    encode,
    valid_id,
)

# The example payloads of WIRE.md, copied verbatim.
WIRE_LASER_SCAN = """{"stamp_ns": 1732300000123456789,
 "angle_min": -3.14159265, "angle_increment": 0.01745329,
 "range_min": 0.05, "range_max": 12.0,
 "ranges": [1.23, null, 4.5],
 "sensor_offset": {"x": 0.0, "y": 0.0, "theta": 0.0}}"""

WIRE_ODOMETRY = """{"stamp_ns": 1732300000100000000, "x": 1.0, "y": 2.0, "theta": 0.1}"""

WIRE_INITIAL_POSE = """{"stamp_ns": 1732300000000000000, "map_id": "warehouse-1", "x": 1.0, "y": 2.0, "theta": 0.0}"""  # noqa: E501

WIRE_POSE_ESTIMATE = """{"stamp_ns": 1732300000123456789, "robot_id": "r1", "map_id": "warehouse-1",
 "x": 1.02, "y": 2.01, "theta": 0.003,
 "status": "tracking", "discrepancy": 0.012, "iterations": 4,
 "covariance": [0.0004, 0, 0, 0, 0.0004, 0, 0, 0, 0.0001]}"""

WIRE_MAP = """{"map_id": "warehouse-1", "version": 3, "frame_id": "map",
 "geometry": {"type": "Polygon",
              "coordinates": [[[0,0],[20,0],[20,10],[0,10],[0,0]],
                              [[5,5],[6,5],[6,6],[5,6],[5,5]]]}}"""

WIRE_EVENT = """{"stamp_ns": 1732300000123456789, "level": "error", "code": "invalid_message",
 "key": "rlutf/robots/r1/scan", "message": "ranges[17]: input should be a number or null"}"""


def test_wire_laser_scan_example_decodes() -> None:
    scan = decode(LaserScan, WIRE_LASER_SCAN)
    assert scan.stamp_ns == 1732300000123456789
    assert scan.angle_min == -3.14159265
    assert scan.angle_increment == 0.01745329
    assert (scan.range_min, scan.range_max) == (0.05, 12.0)
    assert scan.ranges == (1.23, None, 4.5)
    assert scan.sensor_offset == SensorOffset(x=0.0, y=0.0, theta=0.0)


def test_wire_odometry_example_decodes() -> None:
    odom = decode(Odometry, WIRE_ODOMETRY)
    assert (odom.stamp_ns, odom.x, odom.y, odom.theta) == (1732300000100000000, 1.0, 2.0, 0.1)


def test_wire_initial_pose_example_decodes() -> None:
    pose = decode(InitialPose, WIRE_INITIAL_POSE)
    assert pose.map_id == "warehouse-1"
    assert (pose.stamp_ns, pose.x, pose.y, pose.theta) == (1732300000000000000, 1.0, 2.0, 0.0)


def test_wire_pose_estimate_example_decodes() -> None:
    pose = decode(PoseEstimate, WIRE_POSE_ESTIMATE)
    assert (pose.robot_id, pose.map_id, pose.status) == ("r1", "warehouse-1", "tracking")
    assert (pose.x, pose.y, pose.theta) == (1.02, 2.01, 0.003)
    assert (pose.discrepancy, pose.iterations) == (0.012, 4)
    assert pose.covariance == (0.0004, 0.0, 0.0, 0.0, 0.0004, 0.0, 0.0, 0.0, 0.0001)
    assert all(isinstance(value, float) for value in pose.covariance)


def test_wire_map_example_decodes() -> None:
    map_ = decode(Map, WIRE_MAP)
    assert (map_.map_id, map_.version, map_.frame_id) == ("warehouse-1", 3, "map")
    assert isinstance(map_.geometry, Polygon)
    exterior, hole = map_.geometry.coordinates
    assert exterior == ((0.0, 0.0), (20.0, 0.0), (20.0, 10.0), (0.0, 10.0), (0.0, 0.0))
    assert hole[2] == (6.0, 6.0)
    assert map_.geometry.polygons == (map_.geometry.coordinates,)


def test_wire_event_example_decodes() -> None:
    event = decode(Event, WIRE_EVENT)
    assert (event.level, event.code) == ("error", EventCode.INVALID_MESSAGE)
    assert event.key == "rlutf/robots/r1/scan"
    assert event.message == "ranges[17]: input should be a number or null"


def test_multipolygon_map_decodes() -> None:
    square = "[[0,0],[1,0],[1,1],[0,1],[0,0]]"
    far = "[[5,5],[6,5],[6,6],[5,5]]"
    payload = (
        '{"map_id": "m", "version": 0, "geometry": {"type": "MultiPolygon", '
        f'"coordinates": [[{square}], [{far}]]}}}}'
    )
    map_ = decode(Map, payload)
    assert isinstance(map_.geometry, MultiPolygon)
    assert len(map_.geometry.polygons) == 2
    assert map_.frame_id == "map"


def test_optional_fields_take_their_defaults() -> None:
    scan = decode(
        LaserScan,
        '{"stamp_ns": 0, "angle_min": 0, "angle_increment": -0.1, "range_min": 0,'
        ' "range_max": 1, "ranges": [null]}',
    )
    assert scan.sensor_offset == SensorOffset()
    assert (scan.sensor_offset.x, scan.sensor_offset.y, scan.sensor_offset.theta) == (0, 0, 0)
    pose = decode(PoseEstimate, WIRE_POSE_ESTIMATE.replace(',\n "covariance"', ', "_c"'))
    assert pose.covariance is None
    event = decode(Event, '{"stamp_ns": 1, "level": "info", "code": "lost"}')
    assert (event.key, event.message) == ("", "")
    health = decode(Health, '{"instance": "a"}')
    assert (health.robots, health.received, health.latency_ms.p99, health.extra) == (0, 0, 0, {})


def test_unknown_fields_are_ignored_at_every_level() -> None:
    payload = WIRE_LASER_SCAN.replace(
        '"sensor_offset": {', '"intensities": [1, 2], "sensor_offset": {"z": 3, '
    )
    assert decode(LaserScan, payload) == decode(LaserScan, WIRE_LASER_SCAN)
    map_payload = WIRE_MAP.replace('{"type"', '{"bbox": [0, 0, 20, 10], "type"')
    assert decode(Map, map_payload) == decode(Map, WIRE_MAP)
    assert b"intensities" not in encode(decode(LaserScan, payload))


def test_models_are_frozen() -> None:
    odom = decode(Odometry, WIRE_ODOMETRY)
    with pytest.raises(ValidationError):
        odom.x = 3.0
    assert hash(odom) == hash(decode(Odometry, WIRE_ODOMETRY))


def test_python_callers_may_pass_lists_and_ints() -> None:
    pose = PoseEstimate(
        stamp_ns=5,
        robot_id="r1",
        map_id="m",
        x=1,
        y=2,
        theta=0,
        status="corrected",
        discrepancy=0,
        iterations=3,
        covariance=[1, 0, 0, 0, 1, 0, 0, 0, 1],  # type: ignore[arg-type]
    )
    assert isinstance(pose.x, float)
    assert pose.covariance == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def test_scan_constraints() -> None:
    base = {
        "stamp_ns": 1,
        "angle_min": 0.0,
        "angle_increment": 0.1,
        "range_min": 0.1,
        "range_max": 5.0,
        "ranges": [1.0],
    }
    LaserScan(**base)  # type: ignore[arg-type]
    for field, value in [
        ("angle_increment", 0.0),
        ("range_min", -0.1),
        ("range_max", 0.1),
        ("range_max", 0.05),
        ("ranges", []),
        ("ranges", [1.0] * (MAX_BEAMS + 1)),
        ("stamp_ns", -1),
        ("stamp_ns", 2**63),
    ]:
        with pytest.raises(ValidationError) as info:
            LaserScan(**{**base, field: value})  # type: ignore[arg-type]
        assert info.value.errors()[0]["loc"][0] == field
    assert len(LaserScan(**{**base, "ranges": [None] * MAX_BEAMS}).ranges) == MAX_BEAMS  # type: ignore[arg-type]


def test_covariance_needs_exactly_nine_finite_numbers() -> None:
    for covariance in ([0.0] * 8, [0.0] * 10, [0.0] * 8 + [math.inf]):
        with pytest.raises(ValidationError):
            PoseEstimate(
                stamp_ns=1,
                robot_id="r",
                map_id="m",
                x=0,
                y=0,
                theta=0,
                status="lost",
                discrepancy=0,
                iterations=0,
                covariance=covariance,  # type: ignore[arg-type]
            )


@pytest.mark.parametrize("text", ["r1", "warehouse-1", "A_b-9", "x" * 64, "0", "-", "_"])
def test_valid_ids(text: str) -> None:
    assert valid_id(text)
    InitialPose(stamp_ns=0, map_id=text, x=0, y=0, theta=0)


@pytest.mark.parametrize(
    "text",
    ["", "x" * 65, "r 1", "r1\n", "\nr1", "r/1", "r.1", "r*", "rö", "r١", "**", "r1\x00"],
)
def test_invalid_ids(text: str) -> None:
    assert not valid_id(text)
    with pytest.raises(ValidationError):
        InitialPose(stamp_ns=0, map_id=text, x=0, y=0, theta=0)


def test_valid_id_rejects_non_strings() -> None:
    assert not valid_id(None)  # type: ignore[arg-type]
    assert not valid_id(b"r1")  # type: ignore[arg-type]
    assert ID_PATTERN == "[A-Za-z0-9_-]{1,64}"


def test_event_codes_cover_wire_md() -> None:
    required = {
        "invalid_message",
        "invalid_key",
        "map_not_found",
        "invalid_map",
        "not_initialized",
        "lost",
    }
    assert required <= KNOWN_EVENT_CODES
    assert {"scan_dropped", "recorder_overflow", "map_updated"} <= KNOWN_EVENT_CODES
    # The code is a plain string: a code this version does not know still decodes.
    event = decode(Event, '{"stamp_ns": 1, "level": "warning", "code": "from_the_future"}')
    assert event.code == "from_the_future"


def test_health_has_the_wire_md_figures() -> None:
    health = Health(
        instance="svc-a",
        uptime_s=12.5,
        robots=3,
        received=100,
        rejected=2,
        processed=90,
        dropped=8,
        latency_ms={"p50": 1.0, "p90": 2.0, "p99": 3.5, "max": 9.0, "count": 90},  # type: ignore[arg-type]
        extra={"workers": 4, "maps": ["a", "b"], "nested": {"x": None}},
    )
    assert decode(Health, encode(health)) == health
    with pytest.raises(ValidationError):
        Health(instance="a", extra={"bad": [math.nan]})
    with pytest.raises(ValidationError):
        Health(instance="")
