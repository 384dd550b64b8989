"""Recorded poses matched to recomputed ones as a replay goes, in memory that does not grow
with the log.

A replay meets both kinds of pose in ``log_time`` order: the recomputed pose of a scan when the
scan is handled, the recorded pose a moment later (the live service published it after it
received the scan). :class:`PoseMatch` pairs them per robot by the stamp of the scan they
answer, each side first in first out among equal stamps (the pairing of
:func:`service.logs.audit.audit`, whatever the order the two sides arrive in), folds each pair
into the robot's counts at once and keeps only the poses still waiting for their other half:
in a log that passes, the poses of the last moment. A log of a day, 100 robots at 10 Hz, is 86
million poses (about 2 KB each held as records): the audit of such a run could not be held in
memory, its counts can. Poses that never find their other half (a failing audit) wait until
the end, where they count as missing, extra or unverified (:mod:`service.logs.audit`).
"""

from __future__ import annotations

import json
import math
from collections import deque
from typing import Any, NamedTuple

from rlutf.motion import wrap_scalar


class PoseRecord(NamedTuple):
    """One PoseEstimate, recorded or recomputed."""

    robot: str
    stamp_ns: int
    map_id: str
    x: float
    y: float
    theta: float
    status: str
    payload: bytes
    log_time_ns: int = 0
    """When the input it answers was received (a recomputed pose's; 0: not known)."""


#: The fields a pair is matched on (``robot_id``, ``stamp_ns``), judged apart (``x``, ``y``,
#: ``theta`` against the tolerances, ``status`` exactly), or none of the pose's.
_JUDGED_APART = frozenset({"robot_id", "stamp_ns", "x", "y", "theta", "status"})

#: At most this many field names are told apart per robot; further ones are counted together
#: (a tampered log may add a new key to every pose: the counts must not grow with the log).
MAX_FIELDS = 16
OTHER_FIELDS = "(other fields)"


def _deviation(a: Any, b: Any) -> float:
    """How far two JSON values lie apart: the largest difference of their numbers, and
    infinity where anything else differs (a string, a key, a list's length, a type)."""
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers):
        if isinstance(a, bool) or isinstance(b, bool):
            return 0.0 if a is b else math.inf
        if a == b:
            return 0.0
        d = abs(float(a) - float(b))
        return math.inf if math.isnan(d) else d  # inf against inf, or a NaN: no distance
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return math.inf
        return max((_deviation(u, v) for u, v in zip(a, b, strict=True)), default=0.0)
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return math.inf
        return max((_deviation(a[k], b[k]) for k in a), default=0.0)
    return 0.0 if type(a) is type(b) and a == b else math.inf


def _object(payload: bytes) -> dict[str, Any] | None:
    try:
        value = json.loads(payload)
    except (ValueError, RecursionError):
        return None
    return value if isinstance(value, dict) else None


def field_deviations(recorded: bytes, recomputed: bytes) -> dict[str, float]:
    """Per field of two PoseEstimate payloads other than those judged apart, how far they
    differ (:func:`_deviation`), for the fields that differ: ``map_id``, the covariance, the
    quality fields, the hypotheses, a key on one side only (``payload`` when only one of
    them is a JSON object). Empty when neither is (the audit's own tests feed made-up
    payloads; a replay's are PoseEstimates, both decoded already)."""
    a, b = _object(recorded), _object(recomputed)
    if a is None or b is None:
        return {} if a is b else {"payload": math.inf}
    found: dict[str, float] = {}
    for key in (a.keys() | b.keys()) - _JUDGED_APART:
        try:
            d = _deviation(a[key], b[key]) if key in a and key in b else math.inf
        except RecursionError:  # nested deeper than Python recurses: they differ
            d = math.inf
        if d > 0.0:
            found[key] = d
    return found


class Tally:
    """One robot's counts and the poses waiting for their other half, per stamp."""

    __slots__ = (
        "after_gap",
        "fields",
        "identical",
        "last_recorded",
        "matched",
        "max_heading",
        "max_translation",
        "recomputed",
        "recorded",
        "status_differs",
        "sum_heading_sq",
        "sum_translation_sq",
    )

    def __init__(self) -> None:
        self.recorded: dict[int, deque[PoseRecord]] = {}
        self.recomputed: dict[int, deque[PoseRecord]] = {}
        self.matched = self.identical = self.status_differs = self.after_gap = 0
        self.max_translation = self.sum_translation_sq = 0.0
        self.max_heading = self.sum_heading_sq = 0.0
        self.last_recorded: int | None = None
        # Per field other than the pose and status: the pairs it differs in and by how much
        # at most. Before, only x, y, theta and status were compared: a recorded pose moved
        # to another map_id, or given a wider deviation_range or another covariance,
        # passed the audit.
        self.fields: dict[str, tuple[int, float]] = {}

    def compare(self, rec: PoseRecord, new: PoseRecord) -> None:
        dt = math.hypot(new.x - rec.x, new.y - rec.y)
        dh = abs(wrap_scalar(new.theta - rec.theta))
        same = new.payload == rec.payload
        self.matched += 1
        self.identical += same
        self.status_differs += new.status != rec.status
        if not same:  # parsed only where the bytes differ: never in a log that passes
            for field, d in field_deviations(rec.payload, new.payload).items():
                name = (
                    field if field in self.fields or len(self.fields) < MAX_FIELDS else OTHER_FIELDS
                )
                n, most = self.fields.get(name, (0, 0.0))
                self.fields[name] = (n + 1, max(most, d))
        self.max_translation = max(self.max_translation, dt)
        self.max_heading = max(self.max_heading, dh)
        self.sum_translation_sq += dt * dt
        self.sum_heading_sq += dh * dh


def _pair(
    others: dict[int, deque[PoseRecord]], mine: dict[int, deque[PoseRecord]], pose: PoseRecord
) -> PoseRecord | None:
    """The oldest pose of ``others`` with ``pose``'s stamp, taken out; with none, ``pose``
    waits in ``mine`` for its other half and ``None`` is returned."""
    queue = others.get(pose.stamp_ns)
    if not queue:
        mine.setdefault(pose.stamp_ns, deque()).append(pose)
        return None
    other = queue.popleft()
    if not queue:
        del others[pose.stamp_ns]
    return other


class PoseMatch:
    """Recorded and recomputed poses, fed in any interleaving, compared as pairs arrive.

    Args:
        gap_ns: when the log's first recording gap began, if it has one: poses stamped from
            then on are not compared (recorded ones are counted as ``after_gap``).
    """

    def __init__(self, gap_ns: int | None = None) -> None:
        self.gap_ns = gap_ns
        self.end_ns: int | None = None
        """The log's last ``log_time``, once the replay has read it all (see
        :data:`service.logs.audit.TAIL_NS`)."""
        self.robots: dict[str, Tally] = {}
        self.recorded_total = 0
        self.recomputed_total = 0

    def tally(self, robot: str) -> Tally:
        """The counts of ``robot`` (made empty the first time)."""
        r = self.robots.get(robot)
        if r is None:
            r = self.robots[robot] = Tally()
        return r

    def _after_gap(self, stamp_ns: int) -> bool:
        return self.gap_ns is not None and stamp_ns >= self.gap_ns

    def recorded(self, pose: PoseRecord) -> None:
        """A pose the log holds."""
        self.recorded_total += 1
        r = self.tally(pose.robot)
        if self._after_gap(pose.stamp_ns):
            r.after_gap += 1
            return
        if r.last_recorded is None or pose.stamp_ns > r.last_recorded:
            r.last_recorded = pose.stamp_ns
        new = _pair(r.recomputed, r.recorded, pose)
        if new is not None:
            r.compare(pose, new)

    def recomputed(self, pose: PoseRecord) -> None:
        """A pose the replay computed."""
        self.recomputed_total += 1
        r = self.tally(pose.robot)
        if self._after_gap(pose.stamp_ns):
            return
        rec = _pair(r.recorded, r.recomputed, pose)
        if rec is not None:
            r.compare(rec, pose)

    def merge(self, other: PoseMatch) -> None:
        """Take in the counts of ``other``, a match of other robots (an audit split by robot).

        Raises:
            ValueError: the two matched a robot both.
        """
        shared = self.robots.keys() & other.robots.keys()
        if shared:
            raise ValueError(f"both matches hold robots {sorted(shared)}")
        self.robots.update(other.robots)
        if other.end_ns is not None:
            self.end_ns = max(self.end_ns or 0, other.end_ns)
        self.recorded_total += other.recorded_total
        self.recomputed_total += other.recomputed_total

    def waiting(self) -> int:
        """Poses held for their other half (the memory the matching takes)."""
        return sum(
            len(q) for r in self.robots.values() for side in (r.recorded, r.recomputed)
            for q in side.values()
        )  # fmt: skip
