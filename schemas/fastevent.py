"""The Event a dropped scan leaves in the log, written without building the model.

A service that falls behind drops the older of two waiting scans of a robot and records an Event
``scan_dropped`` for each (WIRE.md: replay drops the same scans). Building the pydantic model
and running :func:`schemas.encode` over it cost ~10 us a drop, on the thread that is already
behind: the more it dropped, the more each further drop cost. :func:`encode_scan_dropped`
writes the same bytes from a template (the key escaped as ``json.dumps`` escapes it);
``tests/schemas/test_fastevent.py`` compares the two byte for byte.
"""

from __future__ import annotations

import json

from schemas._types import MAX_STAMP_NS
from schemas.codec import encode
from schemas.messages import Event, EventCode


def scan_dropped_message(stamp_ns: int) -> str:
    """The Event's text for the scan stamped ``stamp_ns``."""
    return f"scan {stamp_ns} replaced by a newer scan before processing"


def encode_scan_dropped(key: str, stamp_ns: int) -> bytes:
    """``encode(Event(...))`` of the ``scan_dropped`` Event of the scan at ``key`` stamped
    ``stamp_ns``: the same bytes, faster."""
    if type(stamp_ns) is int and 0 <= stamp_ns <= MAX_STAMP_NS and type(key) is str:
        quoted = json.dumps(key, ensure_ascii=False)
        text = (
            f'{{"stamp_ns":{stamp_ns},"level":"info","code":"{EventCode.SCAN_DROPPED}",'
            f'"key":{quoted},"message":"{scan_dropped_message(stamp_ns)}"}}'
        )
        try:
            return text.encode()
        except UnicodeEncodeError:  # a lone surrogate: the model says what is wrong
            pass
    return encode(
        Event(
            stamp_ns=stamp_ns,
            level="info",
            code=EventCode.SCAN_DROPPED,
            key=key,
            message=scan_dropped_message(stamp_ns),
        )
    )
