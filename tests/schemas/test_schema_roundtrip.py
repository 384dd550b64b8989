"""Round trips: encode then decode gives the message back, and the bytes are stable."""

from __future__ import annotations

import json
import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import (
    MAX_STAMP_NS,
    Event,
    Health,
    InitialPose,
    LaserScan,
    LatencyPercentiles,
    Map,
    MultiPolygon,
    Odometry,
    Polygon,
    PoseEstimate,
    SensorOffset,
    WireModel,
    decode,
    encode,
)

finite = st.floats(allow_nan=False, allow_infinity=False)
non_negative = st.floats(min_value=0.0, allow_nan=False, allow_infinity=False)
stamps = st.integers(min_value=0, max_value=MAX_STAMP_NS)
counts = st.integers(min_value=0, max_value=2**64)
ids = st.from_regex(r"[A-Za-z0-9_-]{1,64}", fullmatch=True)
texts = st.text(st.characters(exclude_categories=["Cs"]), max_size=80)
offsets = st.builds(SensorOffset, x=finite, y=finite, theta=finite)


@st.composite
def laser_scans(draw: st.DrawFn) -> LaserScan:
    range_min = draw(st.floats(min_value=0.0, max_value=1e6))
    range_max = draw(st.floats(min_value=range_min, max_value=1e9, exclude_min=True))
    return LaserScan(
        stamp_ns=draw(stamps),
        angle_min=draw(finite),
        angle_increment=draw(finite.filter(lambda value: value != 0.0)),
        range_min=range_min,
        range_max=range_max,
        ranges=draw(st.lists(st.none() | finite, min_size=1, max_size=400).map(tuple)),
        sensor_offset=draw(offsets),
    )


odometries = st.builds(Odometry, stamp_ns=stamps, x=finite, y=finite, theta=finite)
initial_poses = st.builds(
    InitialPose, stamp_ns=stamps, map_id=ids, x=finite, y=finite, theta=finite
)
pose_estimates = st.builds(
    PoseEstimate,
    stamp_ns=stamps,
    robot_id=ids,
    map_id=ids,
    x=finite,
    y=finite,
    theta=finite,
    status=st.sampled_from(["tracking", "corrected", "lost"]),
    discrepancy=non_negative,
    iterations=counts,
    covariance=st.none() | st.lists(finite, min_size=9, max_size=9),
)
positions = st.tuples(finite, finite)
rings = st.lists(positions, min_size=3, max_size=12).map(lambda ring: [*ring, ring[0]])
polygon_rings = st.lists(rings, min_size=1, max_size=4)
geometries = st.builds(Polygon, type=st.just("Polygon"), coordinates=polygon_rings) | st.builds(
    MultiPolygon,
    type=st.just("MultiPolygon"),
    coordinates=st.lists(polygon_rings, min_size=1, max_size=3),
)
maps = st.builds(Map, map_id=ids, version=counts, frame_id=texts.filter(bool), geometry=geometries)
events = st.builds(
    Event,
    stamp_ns=stamps,
    level=st.sampled_from(["debug", "info", "warning", "error"]),
    code=texts.filter(bool),
    key=texts,
    message=texts,
)
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | finite | texts,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(texts, inner, max_size=4),
    max_leaves=12,
)
healths = st.builds(
    Health,
    instance=texts.filter(bool),
    stamp_ns=st.none() | stamps,
    uptime_s=non_negative,
    robots=counts,
    received=counts,
    rejected=counts,
    processed=counts,
    dropped=counts,
    latency_ms=st.builds(
        LatencyPercentiles,
        p50=non_negative,
        p90=non_negative,
        p99=non_negative,
        max=non_negative,
        count=counts,
    ),
    extra=st.dictionaries(texts, json_values, max_size=5),
)
messages = laser_scans() | odometries | initial_poses | pose_estimates | maps | events | healths


def _assert_round_trip(message: WireModel) -> None:
    payload = encode(message)
    back = decode(type(message), payload, max_bytes=len(payload))
    assert back == message
    # Same floats bit for bit, -0.0 included: re-encoding gives the same bytes.
    assert encode(back) == payload


@settings(max_examples=60)
@given(laser_scans())
def test_laser_scan_round_trip(scan: LaserScan) -> None:
    _assert_round_trip(scan)


@given(odometries)
def test_odometry_round_trip(odom: Odometry) -> None:
    _assert_round_trip(odom)


@given(initial_poses)
def test_initial_pose_round_trip(pose: InitialPose) -> None:
    _assert_round_trip(pose)


@given(pose_estimates)
def test_pose_estimate_round_trip(pose: PoseEstimate) -> None:
    _assert_round_trip(pose)
    assert (b'"covariance"' in encode(pose)) == (pose.covariance is not None)


@settings(max_examples=60)
@given(maps)
def test_map_round_trip(map_: Map) -> None:
    _assert_round_trip(map_)


@given(events)
def test_event_round_trip(event: Event) -> None:
    _assert_round_trip(event)


@given(healths)
def test_health_round_trip(health: Health) -> None:
    _assert_round_trip(health)


@given(messages)
def test_encoding_is_compact_utf8_json(message: WireModel) -> None:
    payload = encode(message)
    text = payload.decode("utf-8")
    parsed = json.loads(text)
    assert isinstance(parsed, dict)
    assert text == json.dumps(parsed, ensure_ascii=False, separators=(",", ":"))
    assert next(iter(parsed)) == next(iter(type(message).model_fields))


def test_encoding_matches_hand_written_bytes() -> None:
    odom = Odometry(stamp_ns=1732300000100000000, x=1, y=2.0, theta=0.1)
    assert encode(odom) == b'{"stamp_ns":1732300000100000000,"x":1.0,"y":2.0,"theta":0.1}'
    pose = PoseEstimate(
        stamp_ns=7,
        robot_id="r1",
        map_id="m",
        x=1e-05,
        y=-0.0,
        theta=1e16,
        status="lost",
        discrepancy=0.5,
        iterations=0,
    )
    assert encode(pose) == (
        b'{"stamp_ns":7,"robot_id":"r1","map_id":"m","x":1e-05,"y":-0.0,"theta":1e+16,'
        b'"status":"lost","discrepancy":0.5,"iterations":0}'
    )
    event = Event(stamp_ns=1, level="info", code="lost", message="Größe")
    assert encode(event) == (
        '{"stamp_ns":1,"level":"info","code":"lost","key":"","message":"Größe"}'.encode()
    )


def test_free_form_key_order_does_not_change_the_bytes() -> None:
    first = Health(instance="a", extra={"b": {"y": 1, "x": 2}, "a": [{"d": 1, "c": 2}]})
    second = Health(instance="a", extra={"a": [{"c": 2, "d": 1}], "b": {"x": 2, "y": 1}})
    assert first == second
    assert encode(first) == encode(second)
    assert b'"extra":{"a":[{"c":2,"d":1}],"b":{"x":2,"y":1}}' in encode(first)


def test_floats_survive_exactly() -> None:
    tricky = [0.1, 1 / 3, 5e-324, 1.7976931348623157e308, -2.5e-8, 2**53 + 1.0, math.pi]
    scan = LaserScan(
        stamp_ns=0,
        angle_min=-math.pi,
        angle_increment=2 * math.pi / 360,
        range_min=0.0,
        range_max=1.7976931348623157e308,
        ranges=tuple(tricky),
    )
    back = decode(LaserScan, encode(scan))
    assert [value.hex() for value in back.ranges if value is not None] == [
        value.hex() for value in tricky
    ]
    assert back.angle_increment.hex() == scan.angle_increment.hex()


def _plain(message: WireModel) -> dict[str, Any]:
    parsed: dict[str, Any] = json.loads(encode(message))
    return parsed


def test_absent_and_null_optional_fields_decode_alike() -> None:
    pose = PoseEstimate(
        stamp_ns=1,
        robot_id="r",
        map_id="m",
        x=0,
        y=0,
        theta=0,
        status="tracking",
        discrepancy=0,
        iterations=1,
    )
    with_null = json.dumps({**_plain(pose), "covariance": None})
    assert decode(PoseEstimate, with_null) == pose
    assert "stamp_ns" not in _plain(Health(instance="a"))
