"""encode_pose writes the bytes encode(PoseEstimate(...)) writes, and rejects what it rejects."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from schemas import Hypothesis, PoseEstimate, decode, encode
from schemas.fastpose import encode_pose, read_head

floats = st.floats(allow_nan=False, allow_infinity=False, width=64)
ids = st.from_regex(r"\A[A-Za-z0-9_-]{1,64}\Z")


@given(
    st.integers(0, 2**63 - 1),
    ids,
    ids,
    floats,
    floats,
    floats,
    st.sampled_from(["tracking", "corrected", "lost"]),
    st.floats(0, 1e9, allow_nan=False),
    st.integers(0, 10**6),
    st.none() | st.lists(floats, min_size=9, max_size=9),
    st.none() | st.floats(0, 1, allow_nan=False),
    st.none() | st.floats(0, 1e12, allow_nan=False),
)
@settings(max_examples=300, deadline=None)
def test_same_bytes_as_the_model(
    stamp: int,
    robot: str,
    map_id: str,
    x: float,
    y: float,
    theta: float,
    status: str,
    discrepancy: float,
    iterations: int,
    covariance: list[float] | None,
    score: float | None,
    deviation: float | None,
) -> None:
    fields = {
        "stamp_ns": stamp,
        "robot_id": robot,
        "map_id": map_id,
        "x": x,
        "y": y,
        "theta": theta,
        "status": status,
        "discrepancy": discrepancy,
        "iterations": iterations,
        "covariance": covariance,
        "hypotheses": None,
        "localization_score": score,
        "deviation_range": deviation,
    }
    fast = encode_pose(*fields.values())  # type: ignore[arg-type]
    assert fast == encode(PoseEstimate.model_validate(fields))
    assert decode(PoseEstimate, fast) == PoseEstimate.model_validate(fields)


def test_hypotheses_take_the_model_path() -> None:
    h = (Hypothesis(x=1.0, y=2.0, theta=0.5, score=0.9),)
    fast = encode_pose(1, "r1", "m", 1.0, 2.0, 0.5, "lost", 0.1, 3, None, h)
    model = PoseEstimate(
        stamp_ns=1,
        robot_id="r1",
        map_id="m",
        x=1.0,
        y=2.0,
        theta=0.5,
        status="lost",
        discrepancy=0.1,
        iterations=3,
        hypotheses=h,
    )
    assert fast == encode(model)


@pytest.mark.parametrize(
    "change",
    [
        {"x": math.nan},
        {"theta": math.inf},
        {"discrepancy": -0.1},
        {"robot_id": "bad id"},
        {"map_id": ""},
        {"status": "confused"},
        {"stamp_ns": -1},
        {"iterations": -2},
        {"covariance": [0.0] * 8},
        {"covariance": [math.nan] * 9},
        {"localization_score": 1.5},
        {"localization_score": -0.1},
        {"localization_score": math.nan},
        {"deviation_range": -1.0},
        {"deviation_range": math.inf},
    ],
)
def test_out_of_range_raises_as_the_model_does(change: dict[str, object]) -> None:
    fields: dict[str, object] = {
        "stamp_ns": 1,
        "robot_id": "r1",
        "map_id": "m",
        "x": 0.0,
        "y": 0.0,
        "theta": 0.0,
        "status": "tracking",
        "discrepancy": 0.0,
        "iterations": 0,
        "covariance": None,
        "hypotheses": None,
        "localization_score": 0.9,
        "deviation_range": 0.01,
    } | change
    with pytest.raises(ValidationError):
        encode_pose(*fields.values())  # type: ignore[arg-type]
    with pytest.raises(ValidationError):
        PoseEstimate.model_validate(fields)


def test_the_head_of_an_encoded_pose_is_read_without_decoding_the_rest() -> None:
    payload = encode_pose(1_234, "r-1_x", "m", 1.0, 2.0, 0.5, "tracking", 0.1, 3)
    assert read_head(payload) == (1_234, "r-1_x")
    assert payload == encode(decode(PoseEstimate, payload))  # the model writes the same head
    assert read_head(payload[:20] + b"garbage") is None
    assert read_head(b'{"robot_id":"r1","stamp_ns":1,') is None  # another order: decode it
    assert read_head(b'{"stamp_ns":1,"robot_id":"bad id",') is None
