"""Bad input: every kind is a SchemaError whose message names the field and the value."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from schemas import (
    DEFAULT_MAX_BYTES,
    SCHEMA_NAMES,
    EncodeError,
    Event,
    FieldIssue,
    Health,
    InitialPose,
    InvalidMessage,
    InvalidUtf8,
    LaserScan,
    MalformedJson,
    Map,
    Odometry,
    PayloadTooLarge,
    PoseEstimate,
    SchemaError,
    WireModel,
    decode,
    encode,
)

SCAN: dict[str, Any] = {
    "stamp_ns": 1732300000123456789,
    "angle_min": -3.14159265,
    "angle_increment": 0.01745329,
    "range_min": 0.05,
    "range_max": 12.0,
    "ranges": [1.23, None, 4.5],
}
POSE: dict[str, Any] = {
    "stamp_ns": 1,
    "robot_id": "r1",
    "map_id": "warehouse-1",
    "x": 1.0,
    "y": 2.0,
    "theta": 0.0,
    "status": "tracking",
    "discrepancy": 0.0,
    "iterations": 1,
}
SQUARE = [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]]


def _with(base: dict[str, Any], **changes: Any) -> str:
    return json.dumps({**base, **changes})


def _map(coordinates: Any, kind: str = "Polygon", map_id: str = "m") -> str:
    geometry = {"type": kind, "coordinates": coordinates}
    return json.dumps({"map_id": map_id, "version": 1, "geometry": geometry})


def _error(model: type[WireModel], payload: str | bytes, **kwargs: Any) -> SchemaError:
    with pytest.raises(SchemaError) as info:
        decode(model, payload, **kwargs)
    assert isinstance(info.value, ValueError)
    return info.value


def _issue(model: type[WireModel], payload: str | bytes) -> FieldIssue:
    err = _error(model, payload)
    assert isinstance(err, InvalidMessage)
    assert err.model == model.__name__
    return err.issues[0]


def test_message_reads_like_the_wire_md_example() -> None:
    ranges = [1.0] * 17 + ["abc"]
    err = _error(LaserScan, _with(SCAN, ranges=ranges))
    assert str(err) == 'ranges[17]: input should be a number or null, got "abc"'


@pytest.mark.parametrize(
    ("model", "payload", "path", "message", "value"),
    [
        # wrong types, strictly: no str -> number, no bool -> number, no float -> int
        (Odometry, '{"stamp_ns": 1, "x": "1.0", "y": 0, "theta": 0}', "x", "a number", '"1.0"'),
        (Odometry, '{"stamp_ns": 1, "x": true, "y": 0, "theta": 0}', "x", "a number", "true"),
        (Odometry, '{"stamp_ns": 1.0, "x": 0, "y": 0, "theta": 0}', "stamp_ns", "integer", "1.0"),
        (Odometry, '{"stamp_ns": "1", "x": 0, "y": 0, "theta": 0}', "stamp_ns", "integer", '"1"'),
        (
            Odometry,
            '{"stamp_ns": false, "x": 0, "y": 0, "theta": 0}',
            "stamp_ns",
            "integer",
            "false",
        ),
        (Odometry, '{"stamp_ns": -5, "x": 0, "y": 0, "theta": 0}', "stamp_ns", "greater", "-5"),
        (LaserScan, _with(SCAN, ranges=[1, True]), "ranges[1]", "a number or null", "true"),
        (LaserScan, _with(SCAN, ranges="1,2"), "ranges", "an array", '"1,2"'),
        (
            LaserScan,
            _with(SCAN, sensor_offset=[0, 0, 0]),
            "sensor_offset",
            "an object",
            "[0, 0, 0]",
        ),
        (LaserScan, _with(SCAN, sensor_offset={"x": "0"}), "sensor_offset.x", "a number", '"0"'),
        (Event, '{"stamp_ns": 1, "level": "info", "code": 7}', "code", "a string", "7"),
        (Event, '{"stamp_ns": 1, "level": "fatal", "code": "x"}', "level", "'error'", '"fatal"'),
        (PoseEstimate, _with(POSE, status="ok"), "status", "'tracking'", '"ok"'),
        (PoseEstimate, _with(POSE, iterations=1.5), "iterations", "integer", "1.5"),
        (PoseEstimate, _with(POSE, discrepancy=-1), "discrepancy", "greater", "-1"),
        (PoseEstimate, _with(POSE, covariance=[0] * 8), "covariance", "at least 9 items", "[0, "),
        (PoseEstimate, _with(POSE, covariance=[0] * 9 + [1]), "covariance", "at most 9", "[0, "),
        (PoseEstimate, _with(POSE, covariance=[0] * 8 + [None]), "covariance[8]", "number", "null"),
        # constraints
        (LaserScan, _with(SCAN, angle_increment=0), "angle_increment", "not be 0", "0"),
        (LaserScan, _with(SCAN, range_min=-1), "range_min", "greater than or equal", "-1"),
        (LaserScan, _with(SCAN, range_max=0.05), "range_max", "greater than range_min", "0.05"),
        (LaserScan, _with(SCAN, ranges=[]), "ranges", "at least 1 item,", "[]"),
        (LaserScan, _with(SCAN, ranges=[1.0] * 8193), "ranges", "at most 8192 items", "[1.0, "),
        (Map, '{"map_id": "m", "version": -1, "geometry": 1}', "version", "greater", "-1"),
        (Health, '{"instance": "a", "robots": -1}', "robots", "greater", "-1"),
        (
            Health,
            '{"instance": "a", "latency_ms": {"p99": "x"}}',
            "latency_ms.p99",
            "number",
            '"x"',
        ),
        # the document itself
        (Odometry, "[1, 2]", "payload", "an object", "[1, 2]"),
        (Odometry, "null", "payload", "an object", "null"),
        (Odometry, '"odometry"', "payload", "an object", '"odometry"'),
    ],
)
def test_wrong_values_name_field_and_value(
    model: type[WireModel], payload: str, path: str, message: str, value: str
) -> None:
    issue = _issue(model, payload)
    assert issue.path == path
    assert message in issue.message
    assert issue.value is not None
    assert issue.value.startswith(value)
    assert str(issue).startswith(f"{path}: ")


@pytest.mark.parametrize("field", ["stamp_ns", "angle_min", "range_max", "ranges"])
def test_missing_required_field(field: str) -> None:
    payload = json.dumps({key: value for key, value in SCAN.items() if key != field})
    issue = _issue(LaserScan, payload)
    assert (issue.path, issue.message, issue.value) == (field, "field required", None)
    assert str(issue) == f"{field}: field required"


@pytest.mark.parametrize("field", ["stamp_ns", "x", "theta"])
def test_null_in_a_required_field(field: str) -> None:
    payload = _with({"stamp_ns": 1, "x": 0.0, "y": 0.0, "theta": 0.0}, **{field: None})
    issue = _issue(Odometry, payload)
    assert issue.path == field
    assert issue.value == "null"


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999", "-1e999"])
def test_non_finite_numbers_are_rejected(token: str) -> None:
    issue = _issue(Odometry, f'{{"stamp_ns": 1, "x": {token}, "y": 0, "theta": 0}}')
    assert (issue.path, issue.message) == ("x", "input should be a finite number")
    assert issue.value in {"NaN", "Infinity", "-Infinity"}
    raw = json.dumps(SCAN).replace("4.5", token)
    issue = _issue(LaserScan, raw)
    assert (issue.path, issue.message) == ("ranges[2]", "input should be a number or null")
    issue = _issue(
        InitialPose, f'{{"stamp_ns": 0, "map_id": "m", "x": 0, "y": {token}, "theta": 0}}'
    )
    assert issue.path == "y"
    cov = f"[0, 0, 0, 0, {token}, 0, 0, 0, 0]"
    issue = _issue(PoseEstimate, json.dumps(POSE)[:-1] + f', "covariance": {cov}}}')
    assert issue.path == "covariance[4]"
    issue = _issue(Health, f'{{"instance": "a", "extra": {{"load": [{token}]}}}}')
    assert (issue.path, issue.message) == ("extra", "input should be a finite number")


def test_every_issue_is_kept_and_the_message_summarises() -> None:
    err = _error(LaserScan, _with(SCAN, ranges=["a", "b", "c", "d", "e"]))
    assert isinstance(err, InvalidMessage)
    assert [issue.path for issue in err.issues] == [f"ranges[{i}]" for i in range(5)]
    assert str(err).endswith("(and 2 more)")
    assert str(err).count(";") == 2


def test_long_values_are_shortened() -> None:
    issue = _issue(Odometry, _with({"stamp_ns": 1, "y": 0, "theta": 0}, x="z" * 500))
    assert issue.value is not None
    assert len(issue.value) == 40
    assert issue.value.endswith("...")


@pytest.mark.parametrize(
    "payload",
    ["", "   ", "{", '{"stamp_ns": 1,}', "{'stamp_ns': 1}", '{"x": 1} trailing', "nul"],
)
def test_malformed_json(payload: str) -> None:
    err = _error(Odometry, payload)
    assert type(err) is MalformedJson
    assert str(err).startswith("malformed JSON: ")
    assert "line 1 column" in str(err)
    assert isinstance(err.detail, str)


@pytest.mark.parametrize(
    ("payload", "position"),
    [
        (b'{"stamp_ns": 1, "x": "\xff"}', 22),
        (b"\xc3(", 0),
        (b'{"key": "\xed\xa0\x80"}', 9),  # an encoded surrogate is not UTF-8
        ("caf\u00e9 {".encode("latin-1"), 3),
    ],
)
def test_invalid_utf8(payload: bytes, position: int) -> None:
    err = _error(Event, payload)
    assert isinstance(err, InvalidUtf8)
    assert isinstance(err, MalformedJson)
    assert err.position == position
    assert f"invalid UTF-8 at byte {position}" in str(err)


def test_lone_surrogate_in_text_is_malformed() -> None:
    err = _error(Event, '{"stamp_ns": 1, "level": "info", "code": "x", "message": "\ud800"}')
    assert type(err) is MalformedJson


def test_non_ascii_text_is_fine() -> None:
    payload = '{"stamp_ns": 1, "level": "info", "code": "x", "message": "Größe 🙂"}'
    assert decode(Event, payload).message == "Größe 🙂"
    assert decode(Event, payload.encode()).message == "Größe 🙂"


def test_oversized_payload_is_rejected_before_parsing() -> None:
    # Malformed beyond the limit: had it been parsed, the error would be MalformedJson.
    payload = b"{" + b" " * DEFAULT_MAX_BYTES
    err = _error(Odometry, payload)
    assert isinstance(err, PayloadTooLarge)
    assert (err.size, err.limit) == (DEFAULT_MAX_BYTES + 1, DEFAULT_MAX_BYTES)
    assert (
        str(err) == f"payload too large: {DEFAULT_MAX_BYTES + 1} bytes, limit {DEFAULT_MAX_BYTES}"
    )


def test_size_limit_counts_bytes_whatever_the_buffer() -> None:
    payload = _with({"stamp_ns": 1, "x": 0, "y": 0, "theta": 0}, note="é" * 20)
    size = len(payload.encode())
    for buffer in (
        payload,
        payload.encode(),
        bytearray(payload.encode()),
        memoryview(payload.encode()),
    ):
        assert decode(Odometry, buffer, max_bytes=size).x == 0.0
        err = _error(Odometry, buffer, max_bytes=size - 1)  # type: ignore[arg-type]
        assert isinstance(err, PayloadTooLarge)
        assert err.size == size


def test_bad_map_geometry() -> None:
    unclosed = [[[0, 0], [1, 0], [1, 1], [0, 1]]]
    issue = _issue(Map, _map(unclosed))
    assert issue.path == "geometry.coordinates[0]"
    assert issue.message.startswith("ring is not closed")
    assert "[0.0, 0.0]" in issue.message
    assert "[0.0, 1.0]" in issue.message

    triangle_without_area = [[[0, 0], [1, 0], [0, 0]]]
    issue = _issue(Map, _map(triangle_without_area))
    assert (issue.path, issue.message) == (
        "geometry.coordinates[0]",
        "array should have at least 4 items, not 3",
    )

    err = _error(Map, _map([[[0, 0], [1, 0], [1, float("nan")], [0, 1], [0, 0]]]))
    assert isinstance(err, InvalidMessage)
    # Only the bad number, not echoes of it as "too short" rings and polygons.
    assert [str(issue) for issue in err.issues] == [
        "geometry.coordinates[0][2][1]: input should be a finite number, got NaN"
    ]

    issue = _issue(Map, _map([[SQUARE], [[[0, 0], [1, 0], [1, "1"], [0, 0]]]], "MultiPolygon"))
    assert issue.path == "geometry.coordinates[1][0][2][1]"

    issue = _issue(Map, _map([[[0, 0, 0], [1, 0], [1, 1], [0, 0]]]))
    assert (issue.path, issue.message) == (
        "geometry.coordinates[0][0]",
        "array should have at most 2 items, not 3",
    )
    issue = _issue(Map, _map([[[0], [1, 0], [1, 1], [0]]]))
    assert issue.path == "geometry.coordinates[0][0][1]"
    assert issue.message == "field required"

    assert _issue(Map, _map([])).path == "geometry.coordinates"
    assert _issue(Map, _map([[]])).path == "geometry.coordinates[0]"
    assert _issue(Map, _map(SQUARE, "MultiPolygon")).path.startswith("geometry.coordinates[0]")

    issue = _issue(Map, _map([0, 0], "Point"))
    assert issue.path == "geometry"
    assert "'Point'" in issue.message
    issue = _issue(Map, '{"map_id": "m", "version": 1, "geometry": {"coordinates": []}}')
    assert issue.path == "geometry"
    assert "'type'" in issue.message


@pytest.mark.parametrize("bad_id", ["", "a b", "r1/scan", "x" * 65, "r1\n", "é"])
def test_bad_ids(bad_id: str) -> None:
    issue = _issue(Map, _map([SQUARE], map_id=bad_id))
    assert issue.path == "map_id"
    shown = json.dumps(bad_id, ensure_ascii=False)
    assert issue.value == (shown if len(shown) <= 40 else shown[:37] + "...")
    issue = _issue(PoseEstimate, _with(POSE, robot_id=bad_id))
    assert issue.path == "robot_id"
    issue = _issue(InitialPose, _with({"stamp_ns": 0, "x": 0, "y": 0, "theta": 0}, map_id=bad_id))
    assert issue.path == "map_id"


def test_encode_refuses_what_json_cannot_carry() -> None:
    broken = Odometry.model_construct(stamp_ns=1, x=math.nan, y=0.0, theta=0.0)
    with pytest.raises(EncodeError, match="cannot encode Odometry"):
        encode(broken)
    surrogate = Event(stamp_ns=1, level="info", code="x", message="\ud800")
    with pytest.raises(EncodeError):
        encode(surrogate)


_models = st.sampled_from(list(SCHEMA_NAMES))
_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=5)
        | st.dictionaries(
            st.sampled_from([*SCAN, *POSE, "geometry", "coordinates", "type", "extra"]) | st.text(),
            inner,
            max_size=6,
        )
    ),
    max_leaves=30,
)


@given(_models, st.binary(max_size=200))
def test_arbitrary_bytes_give_a_schema_error_or_a_message(
    model: type[WireModel], data: bytes
) -> None:
    try:
        assert isinstance(decode(model, data), model)
    except SchemaError as err:
        assert str(err)


@given(_models, _json)
def test_arbitrary_json_gives_a_schema_error_or_a_message(
    model: type[WireModel], value: Any
) -> None:
    try:
        message = decode(model, json.dumps(value))
    except SchemaError as err:
        assert str(err)
        if isinstance(err, InvalidMessage):
            assert err.issues
            assert all(issue.path and issue.message for issue in err.issues)
    else:
        assert decode(model, encode(message)) == message
