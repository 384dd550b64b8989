"""What the service answers on its own queryables (docs/wire.md): StoredVersion and RobotsAnswer.

- :class:`StoredVersion` on ``{prefix}/mapversions/{map_id}``: the version of a map the embedded
  map store holds, or of the one removed from it, which a put must beat.
- :class:`RobotsAnswer` on ``{prefix}/service/{instance}/robots``: every robot an instance
  holds, with its latest pose, and those that send scans but have no pose yet.

They are answered, never put or logged. Unlike the messages of :mod:`schemas.messages`, which
:func:`schemas.encode` writes, the service has always written these with pydantic's own JSON
(:func:`encode_answer`: optional fields as ``null``, pydantic's float format), and tools read
those bytes, so that stays their encoding.
"""

from __future__ import annotations

from pydantic import Field

from schemas._types import (
    FiniteFloat,
    Identifier,
    NonEmptyStr,
    NonNegativeFloat,
    NonNegativeInt,
    StampNs,
    UnitFloat,
    WireModel,
)
from schemas.messages import PoseStatus


class StoredVersion(WireModel):
    """The map store's answer on {prefix}/mapversions/{map_id}: the version of a map it holds,
    or of the one removed from it and not put since, which a put must beat, and how many puts
    of the map it took and has not stored yet."""

    map_id: Identifier = Field(description="The map.")
    version: NonNegativeInt | None = Field(
        description="The version held, or removed; null: neither."
    )
    digest: NonEmptyStr | None = Field(
        description="Hex SHA-256 of the canonical encoding of that version (whitespace and key "
        "order do not count); null with a null version."
    )
    removed: bool = Field(
        default=False, description="The map was removed (rlutf map remove) and not put since."
    )
    pending: NonNegativeInt = Field(
        default=0, description="Puts of the map taken and not stored yet."
    )

    @property
    def held(self) -> tuple[int, str] | None:
        """The version to beat and its digest, if any."""
        if self.version is None or self.digest is None:
            return None
        return self.version, self.digest


class RobotState(WireModel):
    """One robot as an instance sees it: its latest pose."""

    robot_id: Identifier = Field(description="The robot.")
    map_id: Identifier = Field(description="Map of the latest pose.")
    status: PoseStatus = Field(description="Status of the latest pose.")
    x: FiniteFloat = Field(description="Latest pose, metres.")
    y: FiniteFloat = Field(description="Latest pose, metres.")
    theta: FiniteFloat = Field(description="Latest pose, radians.")
    age_s: NonNegativeFloat | None = Field(
        default=None,
        description="Seconds since the instance published the latest pose (its clock); null "
        "for a pose the instance holds but did not publish (a seed, a pose from before a "
        "restart).",
    )
    latency_ms: FiniteFloat | None = Field(
        default=None,
        description="The latest pose's scan receipt to publication, milliseconds; null as age_s.",
    )
    owner: Identifier = Field(description="The instance holding the robot.")
    localization_score: UnitFloat | None = Field(
        default=None,
        description="The latest pose's localization score, 0 to 1 (null: the pose has none).",
    )
    deviation_range: NonNegativeFloat | None = Field(
        default=None,
        description="The latest pose's 95 % deviation range, metres (null: the pose has none).",
    )
    sigma_xy_m: NonNegativeFloat | None = Field(
        default=None,
        description="1-sigma position uncertainty (the larger semi-axis of the covariance's "
        "ellipse), metres (null: the pose has no covariance).",
    )
    sigma_theta_rad: NonNegativeFloat | None = Field(
        default=None, description="1-sigma heading uncertainty, radians (null: as sigma_xy_m)."
    )
    refused: NonEmptyStr | None = Field(
        default=None,
        description="The Event code the robot's inputs have been refused with since its latest "
        "pose (stamp_rejected: stamped too far ahead of the service's clock), so that it gets "
        "no pose although it sends; null: none (new, optional).",
    )


class WaitingRobot(WireModel):
    """A robot an instance holds that has no pose yet."""

    robot_id: Identifier = Field(description="The robot.")
    reason: NonEmptyStr = Field(
        description="Why: the Event code not_initialized or map_not_found, no_scan_yet (an "
        "initial pose or a Relocalize taken in, no scan since) or no_returns (its scans have "
        "too few returns to give a pose), stamp_rejected (its inputs are stamped too far ahead of "
        "the service's clock); more may be added."
    )
    age_s: NonNegativeFloat = Field(
        description="Seconds since the latest such Event, or since the initial pose for "
        "no_scan_yet (the instance's clock)."
    )
    owner: Identifier = Field(description="The instance holding the robot.")
    map_id: Identifier | None = Field(
        default=None,
        description="The map of the robot's latest initial pose or Relocalize (null: none given).",
    )


class RobotsAnswer(WireModel):
    """What {prefix}/service/{instance}/robots answers: the robots of one instance."""

    instance: Identifier = Field(description="The answering instance.")
    stamp_ns: StampNs = Field(description="When the answer was made, ns since the Unix epoch.")
    robots: tuple[RobotState, ...] = Field(
        default=(), description="Every robot held with a pose, by robot id."
    )
    waiting: tuple[WaitingRobot, ...] = Field(
        default=(), description="Robots held with no pose yet, by robot id."
    )


def encode_answer(answer: StoredVersion | RobotsAnswer) -> bytes:
    """Render an answer as the service puts it on the bus: compact UTF-8 JSON with every field,
    optional ones as ``null`` (a robot's ``refused`` only in an answer where one has it),
    floats in pydantic's format (``0.000042``, ``1e+16``).

    Args:
        answer: The answer to send.

    Returns:
        The payload.
    """
    if isinstance(answer, RobotsAnswer) and not any(r.refused for r in answer.robots):
        # ``refused`` (optional, newer) only where a robot has it: the bytes stay as they were
        return answer.model_dump_json(exclude={"robots": {"__all__": {"refused"}}}).encode()
    return answer.model_dump_json().encode()
