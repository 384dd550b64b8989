"""The answers to the service's queries (schemas.answers): the bytes the service wrote before
the models moved into ``schemas`` stay the bytes, and encode then decode gives them back."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from schemas import (
    MAX_STAMP_NS,
    InvalidMessage,
    RobotsAnswer,
    RobotState,
    StoredVersion,
    WaitingRobot,
    decode,
    encode_answer,
)

#: Answers and their bytes as ``service.maps.store.StoredVersion`` and
#: ``service.live.robots.RobotsAnswer`` wrote them (commit bc2db30): optional fields as null,
#: pydantic's float format (0.000042, 1e-7, 1e+16), integers given for floats written as floats.
GOLDEN: list[tuple[StoredVersion | RobotsAnswer, bytes]] = [
    (
        StoredVersion(map_id="m1", version=3, digest="ab" * 32, removed=False, pending=2),
        b'{"map_id":"m1","version":3,"digest":"' + b"ab" * 32 + b'","removed":false,"pending":2}',
    ),
    (
        StoredVersion(map_id="nope", version=None, digest=None),
        b'{"map_id":"nope","version":null,"digest":null,"removed":false,"pending":0}',
    ),
    (
        StoredVersion(map_id="gone", version=7, digest="cd" * 32, removed=True),
        b'{"map_id":"gone","version":7,"digest":"' + b"cd" * 32 + b'","removed":true,"pending":0}',
    ),
    (
        RobotsAnswer(
            instance="rlutf-a",
            stamp_ns=1732300000123456789,
            robots=(
                RobotState(
                    robot_id="r1",
                    map_id="warehouse-1",
                    status="tracking",
                    x=1.02,
                    y=-2.01,
                    theta=0.003,
                    age_s=4.2e-05,
                    latency_ms=3.1,
                    owner="rlutf-a",
                    localization_score=0.98,
                    deviation_range=0.004,
                    sigma_xy_m=1e-7,
                    sigma_theta_rad=math.radians(0.5),
                ),
                RobotState(
                    robot_id="r2",
                    map_id="m",
                    status="lost",
                    x=12,
                    y=1e16,
                    theta=-math.pi,
                    owner="rlutf-a",
                ),
            ),
            waiting=(
                WaitingRobot(robot_id="r3", reason="not_initialized", age_s=0.5, owner="rlutf-a"),
                WaitingRobot(
                    robot_id="r4",
                    reason="no_scan_yet",
                    age_s=107,
                    owner="rlutf-a",
                    map_id="warehouse-1",
                ),
            ),
        ),
        b'{"instance":"rlutf-a","stamp_ns":1732300000123456789,"robots":['
        b'{"robot_id":"r1","map_id":"warehouse-1","status":"tracking","x":1.02,"y":-2.01,'
        b'"theta":0.003,"age_s":0.000042,"latency_ms":3.1,"owner":"rlutf-a",'
        b'"localization_score":0.98,"deviation_range":0.004,"sigma_xy_m":1e-7,'
        b'"sigma_theta_rad":0.008726646259971648},'
        b'{"robot_id":"r2","map_id":"m","status":"lost","x":12.0,"y":1e+16,'
        b'"theta":-3.141592653589793,"age_s":null,"latency_ms":null,"owner":"rlutf-a",'
        b'"localization_score":null,"deviation_range":null,"sigma_xy_m":null,'
        b'"sigma_theta_rad":null}],"waiting":['
        b'{"robot_id":"r3","reason":"not_initialized","age_s":0.5,"owner":"rlutf-a",'
        b'"map_id":null},'
        b'{"robot_id":"r4","reason":"no_scan_yet","age_s":107.0,"owner":"rlutf-a",'
        b'"map_id":"warehouse-1"}]}',
    ),
    (
        RobotsAnswer(instance="b", stamp_ns=0),
        b'{"instance":"b","stamp_ns":0,"robots":[],"waiting":[]}',
    ),
]


@pytest.mark.parametrize(("answer", "payload"), GOLDEN)
def test_the_bytes_are_the_ones_the_service_always_answered(
    answer: StoredVersion | RobotsAnswer, payload: bytes
) -> None:
    assert encode_answer(answer) == payload
    assert decode(type(answer), payload) == answer


def test_a_reader_ignores_unknown_fields_and_refuses_what_the_service_never_writes() -> None:
    assert decode(
        StoredVersion, b'{"map_id":"m1","version":1,"digest":"d","later":[1]}'
    ) == StoredVersion(map_id="m1", version=1, digest="d")
    with pytest.raises(InvalidMessage, match="version"):
        decode(StoredVersion, b'{"map_id":"m1","version":-1,"digest":"d"}')
    with pytest.raises(InvalidMessage, match=r"robots\[0\]\.x"):
        decode(
            RobotsAnswer,
            b'{"instance":"a","stamp_ns":1,"robots":[{"robot_id":"r1","map_id":"m",'
            b'"status":"tracking","x":"1","y":0,"theta":0,"owner":"a"}]}',
        )


finite = st.floats(allow_nan=False, allow_infinity=False)
non_negative = st.floats(min_value=0.0, allow_nan=False, allow_infinity=False)
ids = st.from_regex(r"[A-Za-z0-9_-]{1,64}", fullmatch=True)
states = st.builds(
    RobotState,
    robot_id=ids,
    map_id=ids,
    status=st.sampled_from(["tracking", "corrected", "lost"]),
    x=finite,
    y=finite,
    theta=finite,
    age_s=st.none() | non_negative,
    latency_ms=st.none() | finite,
    owner=ids,
    localization_score=st.none() | st.floats(min_value=0.0, max_value=1.0),
    deviation_range=st.none() | non_negative,
    sigma_xy_m=st.none() | non_negative,
    sigma_theta_rad=st.none() | non_negative,
)
waiting = st.builds(
    WaitingRobot,
    robot_id=ids,
    reason=st.sampled_from(["not_initialized", "map_not_found", "no_scan_yet", "no_returns"]),
    age_s=non_negative,
    owner=ids,
    map_id=st.none() | ids,
)
answers = st.builds(
    RobotsAnswer,
    instance=ids,
    stamp_ns=st.integers(min_value=0, max_value=MAX_STAMP_NS),
    robots=st.lists(states, max_size=4).map(tuple),
    waiting=st.lists(waiting, max_size=4).map(tuple),
) | st.builds(
    StoredVersion,
    map_id=ids,
    version=st.none() | st.integers(min_value=0, max_value=2**63),
    digest=st.none() | st.text(st.characters(exclude_categories=["Cs"]), min_size=1, max_size=64),
    removed=st.booleans(),
    pending=st.integers(min_value=0, max_value=2**31),
)


@given(answers)
def test_encode_then_decode_gives_the_answer_and_its_bytes_back(
    answer: StoredVersion | RobotsAnswer,
) -> None:
    payload = encode_answer(answer)
    again = decode(type(answer), payload)
    assert again == answer
    assert encode_answer(again) == payload
