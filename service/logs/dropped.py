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
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import TypeVar

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
    drop_events: list[tuple[str, int, Record]] | None = None,
) -> tuple[Counter[tuple[str, int]], list[Record]]:
    """The scans the live service dropped (per robot and stamp) and the events saying so (only
    with ``records_too``: they go into an output log, and a run under overload has many);
    only of the robots ``owns`` (default: every robot).

    Robots the service evicted (Event ``robot_evicted``) are added to ``evictions`` as
    ``(log_time_ns, robot)``, in log order, and their records to the events returned; the
    start of each recording gap (Event ``recording_resumed``, or ``recorder_overflow``: messages
    lost to a full queue; each stamped when the gap began) to ``gaps``. With ``drop_events``,
    each ``scan_dropped`` Event goes there as ``(robot, stamp, record)`` instead of into the
    records returned (:class:`LiveDrops`).
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
                if drop_events is not None:
                    drop_events.append((where.robot, stamp, rec))
                elif records_too:
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


class LiveDrops:
    """The scans the live service dropped, for a replay to drop again (:func:`dropped_scans`).

    A service of :data:`DROPS_AT_RECEIPT` or later logs each ``scan_dropped`` Event at the
    dropped scan's own log_time, which tells apart two scans a robot stamped alike: the scan
    dropped is the one of that robot, stamp and log_time. In an older service's log (the Event
    logged when the drop happened) it is the first scan of that robot and stamp, and the output
    of the replay logs the Event at that scan, as the newer service does, so that the output
    audits alike.

    Attributes:
        records: what an output log holds before the replay's pass (the Events of evictions,
            and of drops logged at their scan).
    """

    def __init__(
        self,
        logs: Sequence[LogFile],
        evictions: list[tuple[int, str]],
        gaps: list[int],
        records_too: bool,
        owns: Callable[[str], bool] | None,
    ) -> None:
        events: list[tuple[str, int, Record]] = []
        self.counts, self.records = dropped_scans(logs, evictions, gaps, records_too, owns, events)
        self._exact: Counter[tuple[str, int, int]] | None = None
        self._waiting: dict[tuple[str, int], deque[Record]] = {}
        if drops_at_receipt([lf.library() for lf in logs]):
            self._exact = Counter((robot, stamp, r.log_time_ns) for robot, stamp, r in events)
            self.records += [r for _, _, r in events] if records_too else []
        elif records_too:
            for robot, stamp, r in events:
                self._waiting.setdefault((robot, stamp), deque()).append(r)

    def take(self, robot: str, stamp_ns: int, log_time_ns: int) -> Record | bool:
        """Whether the scan of ``robot`` stamped ``stamp_ns``, logged at ``log_time_ns``, was
        dropped live (counted off): ``False``, ``True``, or the Event to log at it."""
        key = (robot, stamp_ns)
        if self.counts.get(key, 0) <= 0:
            return False
        if self._exact is not None:
            at = (robot, stamp_ns, log_time_ns)
            if self._exact.get(at, 0) <= 0:
                return False  # another scan of the same stamp: the dropped one comes later
            _take(self._exact, at)
        _take(self.counts, key)
        waiting = self._waiting.get(key)
        if not waiting:
            return True
        e = waiting.popleft()
        return Record(e.topic, e.schema_name, e.payload, log_time_ns, e.publish_time_ns)

    def left(self) -> list[Record]:
        """The Events of drops whose scan the log does not hold, as they were logged."""
        return [e for waiting in self._waiting.values() for e in waiting]


K = TypeVar("K")


def _take(counts: Counter[K], key: K) -> None:
    counts[key] -= 1
    if not counts[key]:
        del counts[key]
