"""encode_scan_dropped writes the bytes encode(Event(...)) writes for a dropped scan."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from schemas import Event, decode, encode
from schemas.errors import EncodeError
from schemas.fastevent import encode_scan_dropped, scan_dropped_message
from schemas.messages import EventCode


def _model(key: str, stamp: int) -> bytes:
    return encode(
        Event(
            stamp_ns=stamp,
            level="info",
            code=EventCode.SCAN_DROPPED,
            key=key,
            message=scan_dropped_message(stamp),
        )
    )


@given(st.text(max_size=80), st.integers(0, 2**63 - 1))
@settings(max_examples=300, deadline=None)
def test_same_bytes_as_the_model(key: str, stamp: int) -> None:
    assert encode_scan_dropped(key, stamp) == _model(key, stamp)


def test_a_lone_surrogate_is_refused_as_the_model_refuses_it() -> None:
    with pytest.raises(EncodeError):
        _model("robots/\ud800/scan", 1)
    with pytest.raises(EncodeError):
        encode_scan_dropped("robots/\ud800/scan", 1)


@pytest.mark.parametrize(
    "key", ["rlutf/robots/r001/scan", 'odd"prefix\\/robots/r-1/scan', "bâtiment/robots/é_1/scan"]
)
def test_a_service_key_round_trips(key: str) -> None:
    got = decode(Event, encode_scan_dropped(key, 1_800_000_000_000_000_000))
    assert got.key == key and got.code == "scan_dropped" and got.level == "info"


def test_a_stamp_out_of_range_is_refused_as_the_model_refuses_it() -> None:
    with pytest.raises(ValidationError):
        encode_scan_dropped("k", -1)
