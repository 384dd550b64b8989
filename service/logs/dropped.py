"""The scans the live service dropped under load, read from a log's Events before a replay.

Under load the live service drops a robot's unprocessed scan when a newer one arrives and
records an Event ``scan_dropped`` (``stamp_ns`` = the dropped scan's stamp) on
``{prefix}/robots/{robot}/events``, after the scan itself; a replay reads those Events first
(:func:`dropped_scans`) and skips the same scans, so live and replay stay identical whatever the
load was. The same pass finds the robots the service evicted and the recording gaps.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Callable, Sequence

from schemas import EventCode
from service.logs.mcapfile import Record
from service.logs.mcapread import LogFile, merged_messages, robot_topic

#: The first version whose service logs a ``scan_dropped`` Event at the dropped scan's own
#: log_time (before, at the moment of the drop).
DROPS_AT_RECEIPT = (0, 5, 3)

EVENT_SCHEMA = "rlutf.Event"
"""The schema of an Event in a log."""
#: The service's Events that mark a recording gap: the log lacks messages from their stamp on.
_GAP_CODES = re.compile(rb'"code":"(?:recording_resumed|recorder_overflow)"')


def dropped_scans(
    logs: Sequence[LogFile],
    evictions: list[tuple[int, str]] | None = None,
    gaps: list[int] | None = None,
    records_too: bool = True,
    owns: Callable[[str], bool] | None = None,
    received: Counter[tuple[str, int, int]] | None = None,
) -> tuple[Counter[tuple[str, int]], list[Record]]:
    """The scans the live service dropped (per robot and stamp) and the events saying so (only
    with ``records_too``: they go into an output log, and a run under overload has many);
    only of the robots ``owns`` (default: every robot).

    Robots the service evicted (Event ``robot_evicted``) are added to ``evictions`` as
    ``(log_time_ns, robot)``, in log order, and their records to the events returned; the
    start of each recording gap (Event ``recording_resumed``, or ``recorder_overflow``: messages
    lost to a full queue; each stamped when the gap began) to ``gaps``; each drop as ``(robot,
    stamp, log_time)`` to ``received`` (a service of :data:`DROPS_AT_RECEIPT` or later logs the
    Event at the dropped scan's own log_time, which tells apart two scans stamped alike).
    """
    drops: Counter[tuple[str, int]] = Counter()
    records = []
    for rec in merged_messages(logs, {EVENT_SCHEMA}):
        where = robot_topic(rec.topic)
        if where is None and gaps is not None and _GAP_CODES.search(rec.payload):
            gaps.append(rec.publish_time_ns)
        if where is None or where.leaf != "events" or (owns is not None and not owns(where.robot)):
            continue
        try:
            data = json.loads(rec.payload)
        except (ValueError, RecursionError):  # a log from elsewhere may hold anything
            continue
        if isinstance(data, dict) and data.get("code") == EventCode.SCAN_DROPPED:
            stamp = data.get("stamp_ns")
            if isinstance(stamp, int):
                drops[(where.robot, stamp)] += 1
                if received is not None:
                    received[(where.robot, stamp, rec.log_time_ns)] += 1
                if records_too:
                    records.append(rec)
        elif (
            isinstance(data, dict)
            and data.get("code") == EventCode.ROBOT_EVICTED
            and evictions is not None
        ):
            evictions.append((rec.log_time_ns, where.robot))
            if records_too:
                records.append(rec)
    return drops, records


def drops_at_receipt(libraries: Sequence[str | None]) -> bool:
    """Whether every log (by its MCAP header's library, ``rlutf 0.5.3``) was written by a service
    that logs its drops at the dropped scan's log_time (:data:`DROPS_AT_RECEIPT`)."""
    for library in libraries:
        match = re.fullmatch(r"rlutf (\d+)\.(\d+)\.(\d+)\S*", library or "")
        if match is None or tuple(int(g) for g in match.groups()) < DROPS_AT_RECEIPT:
            return False
    return bool(libraries)
