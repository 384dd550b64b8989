"""The per-robot view of an instance: ``{prefix}/service/{instance}/robots``, and its client.

The service keeps the latest PoseEstimate payload of every robot it holds; per published pose,
:meth:`RobotView.published` adds only when it was published and the scan's latency (one small
tuple in a dict). The payloads are decoded when someone asks, not per pose.

Answer (JSON, :class:`RobotsAnswer`)::

    {"instance": "rlutf-a", "stamp_ns": 1732300000123456789,
     "robots": [{"robot_id": "r1", "map_id": "warehouse-1", "status": "tracking",
                 "x": 1.02, "y": 2.01, "theta": 0.003, "age_s": 0.04,
                 "latency_ms": 3.1, "owner": "rlutf-a",
                 "localization_score": 0.98, "deviation_range": 0.004}]}

``age_s`` is the instance's clock now minus when the latest pose was published; ``age_s`` and
``latency_ms`` are ``null`` for a pose this instance holds but did not publish (a seed).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterable, Mapping
from typing import NamedTuple

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from schemas import PoseEstimate, SchemaError, decode

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON


def robots_key(prefix: str, instance: str) -> str:
    """The key of an instance's robot view (``*`` for every instance)."""
    return f"{prefix}/service/{instance}/robots"


class RobotState(BaseModel):
    """One robot as an instance sees it."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    robot_id: str = Field(description="Robot id.")
    map_id: str = Field(description="Map of the latest pose.")
    status: str = Field(description="Status of the latest pose: tracking, corrected or lost.")
    x: float = Field(description="Latest pose, metres.")
    y: float = Field(description="Latest pose, metres.")
    theta: float = Field(description="Latest pose, radians.")
    age_s: float | None = Field(
        None, description="Seconds since the latest pose was published (instance's clock)."
    )
    latency_ms: float | None = Field(
        None, description="Latest pose's scan receipt to publication, milliseconds."
    )
    owner: str = Field(description="The instance holding the robot.")
    localization_score: float | None = Field(
        None, description="Latest pose's localization score, 0 to 1 (null: the pose has none)."
    )
    deviation_range: float | None = Field(
        None, description="Latest pose's 95 % deviation range, metres (null: the pose has none)."
    )


class RobotsAnswer(BaseModel):
    """What ``{prefix}/service/{instance}/robots`` answers."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    instance: str = Field(description="The answering instance.")
    stamp_ns: int = Field(description="When the answer was made, ns since the Unix epoch.")
    robots: list[RobotState] = Field(default_factory=list, description="By robot id.")


#: How the status lost reads in an encoded PoseEstimate (compact JSON, as :func:`schemas.encode`
#: writes it): counting lost robots needs no decoding.
_LOST = b'"status":"lost"'


class _Published(NamedTuple):
    at_ns: int  # when the pose was published (service clock)
    latency_ns: int | None  # scan receipt to publication


class RobotView:
    """Per-robot publication times of one instance, and the answer built from them.

    Args:
        instance: the instance's name (``owner`` of every robot).
        poses: the service's latest PoseEstimate payload per robot it holds (read, not copied).
        clock: the service clock, ns since the epoch.
    """

    def __init__(self, instance: str, poses: Mapping[str, bytes], clock: Callable[[], int]) -> None:
        self.instance = instance
        self._poses = poses
        self._clock = clock
        self._published: dict[str, _Published] = {}

    # ------------------------------------------------------------------ hot path
    def published(self, robot: str, at_ns: int, received_ns: int | None) -> None:
        """A pose of ``robot`` was published at ``at_ns`` for a scan received at ``received_ns``."""
        # One assignment: a dict store is atomic under the GIL, so no lock.
        self._published[robot] = _Published(
            at_ns, None if received_ns is None else at_ns - received_ns
        )

    def forget(self, robot: str) -> None:
        """``robot`` is no longer held here (moved to another instance)."""
        self._published.pop(robot, None)

    # ------------------------------------------------------------------ scrape and query time
    def held(self) -> int:
        """Robots with a latest pose held."""
        return len(self._poses)

    def lost(self) -> int:
        """Robots held whose latest pose has status lost."""
        return sum(_LOST in payload for payload in list(self._poses.values()))

    def states(self) -> list[RobotState]:
        """Every robot held, by robot id (its latest pose decoded now)."""
        now = self._clock()
        out: list[RobotState] = []
        # sorted() copies the items in C, under the GIL: safe while poses are published.
        for robot, payload in sorted(self._poses.items()):
            try:
                pose = decode(PoseEstimate, payload)
            except SchemaError:  # our own output: cannot happen unless the wire model changed
                log.warning("robot view: undecodable pose of %s", robot, exc_info=True)
                continue
            seen = self._published.get(robot)
            age = latency = None
            if seen is not None:
                age = max(now - seen.at_ns, 0) / 1e9
                latency = None if seen.latency_ns is None else seen.latency_ns / 1e6
            out.append(
                RobotState(
                    robot_id=robot,
                    map_id=pose.map_id,
                    status=pose.status,
                    x=pose.x,
                    y=pose.y,
                    theta=pose.theta,
                    age_s=age,
                    latency_ms=latency,
                    owner=self.instance,
                    localization_score=pose.localization_score,
                    deviation_range=pose.deviation_range,
                )
            )
        return out

    def answer(self) -> bytes:
        """The encoded :class:`RobotsAnswer` of this instance."""
        return (
            RobotsAnswer(instance=self.instance, stamp_ns=self._clock(), robots=self.states())
            .model_dump_json()
            .encode()
        )

    def on_query(self, query: zenoh.Query) -> None:
        """The queryable's callback: answer on the instance's key."""
        with query:
            query.reply(str(query.key_expr), self.answer(), encoding=JSON)


# ---------------------------------------------------------------------------------- client
def fetch_robots(session: zenoh.Session, prefix: str, timeout: float) -> list[RobotsAnswer]:
    """Every instance's answer on ``{prefix}/service/*/robots`` (undecodable ones skipped)."""
    answers: list[RobotsAnswer] = []
    for reply in session.get(robots_key(prefix, "*"), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            answers.append(RobotsAnswer.model_validate_json(reply.ok.payload.to_bytes()))
        except ValueError:
            log.warning("bad robots answer on %s", reply.ok.key_expr)
    return answers


def merge_robots(answers: Iterable[RobotsAnswer]) -> list[RobotState]:
    """All instances' robots by robot id; a robot two instances hold (during a handover) is
    given once, by the instance that published its pose most recently."""
    best: dict[str, RobotState] = {}
    for answer in answers:
        for state in answer.robots:
            old = best.get(state.robot_id)
            if old is None or _fresher(state, old):
                best[state.robot_id] = state
    return [best[r] for r in sorted(best)]


def _fresher(a: RobotState, b: RobotState) -> bool:
    if a.age_s is None:
        return False
    return b.age_s is None or a.age_s < b.age_s


COLUMNS = (
    "robot",
    "map",
    "status",
    "x",
    "y",
    "theta",
    "score",
    "range m",
    "age s",
    "latency ms",
    "owner",
)


def robots_table(states: Iterable[RobotState]) -> str:
    """A plain-text table of ``states`` (header and one line per robot, columns aligned)."""

    def num(value: float | None, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    rows = [list(COLUMNS)]
    rows += [
        [
            s.robot_id,
            s.map_id,
            s.status,
            num(s.x, 3),
            num(s.y, 3),
            num(s.theta, 3),
            num(s.localization_score, 2),
            num(s.deviation_range, 3),
            num(s.age_s, 2),
            num(s.latency_ms, 1),
            s.owner,
        ]
        for s in states
    ]
    widths = [max(len(r[i]) for r in rows) for i in range(len(COLUMNS))]
    numeric = {3, 4, 5, 6, 7, 8, 9}  # right-aligned
    lines = [
        "  ".join(
            cell.rjust(widths[i]) if i in numeric else cell.ljust(widths[i])
            for i, cell in enumerate(row)
        ).rstrip()
        for row in rows
    ]
    return "\n".join(lines)


def robots_json(states: Iterable[RobotState]) -> str:
    """``states`` as one JSON array."""
    return json.dumps([s.model_dump(mode="json") for s in states])
