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

import math
from collections import deque
from typing import NamedTuple

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


class Tally:
    """One robot's counts and the poses waiting for their other half, per stamp."""

    __slots__ = (
        "after_gap",
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

    def compare(self, rec: PoseRecord, new: PoseRecord) -> None:
        dt = math.hypot(new.x - rec.x, new.y - rec.y)
        dh = abs(wrap_scalar(new.theta - rec.theta))
        self.matched += 1
        self.identical += new.payload == rec.payload
        self.status_differs += new.status != rec.status
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
        self.recorded_total += other.recorded_total
        self.recomputed_total += other.recomputed_total

    def waiting(self) -> int:
        """Poses held for their other half (the memory the matching takes)."""
        return sum(
            len(q) for r in self.robots.values() for side in (r.recorded, r.recomputed)
            for q in side.values()
        )  # fmt: skip
