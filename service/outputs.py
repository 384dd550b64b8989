"""What the engine wants published: :class:`Outbound`, one per pose, event or request.

Its own module so that the engine (:mod:`service.engine`) stays one state machine; the engine
re-exports it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from service.maphealth import Handed

OutKind = Literal["pose", "event", "need_map", "skipped", "evidence"]


@dataclass(frozen=True)
class Outbound:
    """Something the engine wants published.

    Attributes:
        kind: ``pose`` (a PoseEstimate for ``key``), ``event`` (an Event for ``key``),
            ``need_map`` (``map_id`` is wanted from the store; nothing is published),
            ``skipped`` (a scan was not turned into a pose; counted, nothing is published) or
            ``evidence`` (map health evidence handed on,
            :meth:`service.engine.FleetEngine.hand_over`).
        key: the Zenoh key to put on.
        payload: encoded JSON.
        stamp_ns: the message's own stamp (MCAP ``publish_time``).
        robot: the robot concerned, if any.
        map_id: for ``need_map``.
        status: for ``pose``: the pose status.
        received_ns: for ``pose``: when the scan it answers was received.
        evidence: for ``evidence``: the grids counted since the last hand-over.
    """

    kind: OutKind
    key: str
    payload: bytes
    stamp_ns: int
    robot: str | None = None
    map_id: str | None = None
    status: str | None = None
    received_ns: int | None = None
    evidence: tuple[Handed, ...] = ()
