"""WIRE.md v1.1: the Relocalize message, PoseEstimate.hypotheses and the relocalization events."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from schemas import (
    KNOWN_EVENT_CODES,
    MAX_STAMP_NS,
    SCHEMA_NAMES,
    EventCode,
    Hypothesis,
    InvalidMessage,
    PoseEstimate,
    Region,
    Relocalize,
    SchemaError,
    decode,
    encode,
    json_schema,
)

# The example payload of WIRE.md, copied verbatim.
WIRE_RELOCALIZE = """{"stamp_ns": 1732300000000000000, "map_id": "warehouse-1", "region": {"x": 4.0, "y": 2.0, "radius": 3.0}}"""  # noqa: E501

POSE: dict[str, Any] = {
    "stamp_ns": 1,
    "robot_id": "r1",
    "map_id": "warehouse-1",
    "x": 1.0,
    "y": 2.0,
    "theta": 0.0,
    "status": "lost",
    "discrepancy": 0.0,
    "iterations": 1,
}

finite = st.floats(allow_nan=False, allow_infinity=False)
ids = st.from_regex(r"[A-Za-z0-9_-]{1,64}", fullmatch=True)
regions = st.builds(
    Region,
    x=finite,
    y=finite,
    radius=st.floats(min_value=0.0, exclude_min=True, allow_infinity=False),
)
relocalizes = st.builds(
    Relocalize,
    stamp_ns=st.integers(min_value=0, max_value=MAX_STAMP_NS),
    map_id=ids,
    region=st.none() | regions,
)
hypotheses = st.builds(
    Hypothesis, x=finite, y=finite, theta=finite, score=st.floats(min_value=0.0, max_value=1.0)
)


def _region(**region: Any) -> str:
    return json.dumps({"stamp_ns": 1, "map_id": "m", "region": region})


def _issue_path(payload: str, model: type[Relocalize] | type[PoseEstimate] = Relocalize) -> str:
    with pytest.raises(SchemaError) as info:
        decode(model, payload)
    assert isinstance(info.value, InvalidMessage)
    return info.value.issues[0].path


def test_wire_relocalize_example_decodes() -> None:
    msg = decode(Relocalize, WIRE_RELOCALIZE)
    assert (msg.stamp_ns, msg.map_id) == (1732300000000000000, "warehouse-1")
    assert msg.region == Region(x=4.0, y=2.0, radius=3.0)


def test_region_is_optional_and_omitted_when_absent() -> None:
    msg = decode(Relocalize, '{"stamp_ns": 5, "map_id": "m"}')
    assert msg.region is None
    assert encode(msg) == b'{"stamp_ns":5,"map_id":"m"}'
    assert decode(Relocalize, '{"stamp_ns": 5, "map_id": "m", "region": null}') == msg


@given(relocalizes)
def test_relocalize_round_trip(msg: Relocalize) -> None:
    payload = encode(msg)
    back = decode(Relocalize, payload)
    assert back == msg
    assert encode(back) == payload


@pytest.mark.parametrize(
    ("payload", "path"),
    [
        (
            '{"stamp_ns": 1, "map_id": "m", "region": {"x": 0, "y": 0, "radius": 0}}',
            "region.radius",
        ),
        (
            '{"stamp_ns": 1, "map_id": "m", "region": {"x": 0, "y": 0, "radius": -2}}',
            "region.radius",
        ),
        ('{"stamp_ns": 1, "map_id": "m", "region": {"x": NaN, "y": 0, "radius": 1}}', "region.x"),
        (
            '{"stamp_ns": 1, "map_id": "m", "region": {"x": 0, "y": 0, "radius": Infinity}}',
            "region.radius",
        ),
        ('{"stamp_ns": 1, "map_id": "m", "region": {"x": "0", "y": 0, "radius": 1}}', "region.x"),
        ('{"stamp_ns": 1, "map_id": "m", "region": {"x": 0, "radius": 1}}', "region.y"),
        ('{"stamp_ns": 1, "map_id": "m", "region": [0, 0, 1]}', "region"),
        ('{"stamp_ns": 1, "map_id": "bad id"}', "map_id"),
        ('{"stamp_ns": 1, "map_id": 7}', "map_id"),
        ('{"stamp_ns": 1.5, "map_id": "m"}', "stamp_ns"),
        ('{"map_id": "m"}', "stamp_ns"),
        ('{"stamp_ns": 1}', "map_id"),
    ],
)
def test_bad_relocalize_names_the_field(payload: str, path: str) -> None:
    assert _issue_path(payload) == path


@given(st.lists(hypotheses, min_size=1, max_size=6))
def test_pose_estimate_hypotheses_round_trip(hyps: list[Hypothesis]) -> None:
    pose = PoseEstimate(**POSE, hypotheses=tuple(hyps))
    payload = encode(pose)
    assert decode(PoseEstimate, payload) == pose
    assert json.loads(payload)["hypotheses"][0] == {
        "x": hyps[0].x,
        "y": hyps[0].y,
        "theta": hyps[0].theta,
        "score": hyps[0].score,
    }


def test_hypotheses_are_omitted_when_none() -> None:
    pose = PoseEstimate(**POSE)
    assert pose.hypotheses is None
    assert b"hypotheses" not in encode(pose)


@pytest.mark.parametrize(
    ("hyp", "path"),
    [
        ({"x": 0, "y": 0, "theta": 0, "score": 1.5}, "hypotheses[0].score"),
        ({"x": 0, "y": 0, "theta": 0, "score": -0.1}, "hypotheses[0].score"),
        ({"x": 0, "y": 0, "theta": 0}, "hypotheses[0].score"),
        ({"x": 0, "y": None, "theta": 0, "score": 0.5}, "hypotheses[0].y"),
    ],
)
def test_bad_hypotheses_are_rejected(hyp: dict[str, Any], path: str) -> None:
    assert _issue_path(json.dumps({**POSE, "hypotheses": [hyp]}), PoseEstimate) == path


def test_relocalize_schema_is_registered_with_its_constraints() -> None:
    assert SCHEMA_NAMES[Relocalize] == "rlutf.Relocalize"
    schema = json_schema(Relocalize)
    assert schema["required"] == ["stamp_ns", "map_id"]
    region = next(o for o in schema["properties"]["region"]["anyOf"] if o.get("type") == "object")
    assert region["properties"]["radius"]["exclusiveMinimum"] == 0.0
    assert set(region["required"]) == {"x", "y", "radius"}
    hyps = json_schema(PoseEstimate)["properties"]["hypotheses"]
    items = next(o for o in hyps["anyOf"] if o.get("type") == "array")["items"]
    assert items["properties"]["score"]["maximum"] == 1.0


def test_relocalization_event_codes() -> None:
    assert (EventCode.RELOCALIZING, EventCode.RELOCALIZED, EventCode.AMBIGUOUS) == (
        "relocalizing",
        "relocalized",
        "ambiguous",
    )
    assert {"relocalizing", "relocalized", "ambiguous"} <= KNOWN_EVENT_CODES
