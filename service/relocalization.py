"""Operator requests that place a robot on a map, and the events of a relocalization episode.

An InitialPose or a Relocalize names a map. A robot that is already localized keeps its pose and
map until that map is loaded (WIRE.md v1.1: an operator's typo must not take a tracking robot off
its map); the request waits as a :class:`Request` and applies at the robot's first input for
which the map is loaded, or is abandoned :data:`REQUEST_WAIT_NS` after it was received. Both
rules read only receive times, so replay decides as the live service did.

A relocalization *episode* starts with a Relocalize, or with a localizer result that relocalizes
after ``lost`` updates (automatic recovery: ``LocalizerConfig.relocalize_after``), and ends at
the result that is ``corrected`` with no hypotheses left, or at an InitialPose that places the
robot meanwhile. :class:`Episode` turns the results into the Events ``relocalizing`` (once, at the
start), ``ambiguous`` (once, the first time several hypotheses remain) and ``relocalized`` (once,
at the end; :func:`placed_during` when an InitialPose ends it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from rlutf.localizer import LocalizeResult
from schemas import EventCode, Hypothesis

FloatArray = np.ndarray
Level = Literal["info", "warning", "error"]

#: How long a request waits for its map (by receive time) when the robot is localized elsewhere;
#: far longer than a map get takes, short enough that a typo'd id cannot move the robot later.
REQUEST_WAIT_NS = 30_000_000_000

#: Hypotheses named in the message of an Event ``ambiguous``.
_NAMED = 3


@dataclass(frozen=True)
class Request:
    """An InitialPose or Relocalize waiting for its map.

    Attributes:
        kind: ``initialpose`` or ``relocalize``.
        map_id: the map it names.
        stamp_ns: its stamp.
        received_ns: when it was received.
        pose: ``(3,)`` the InitialPose's pose; for a Relocalize the region's centre (or zero),
            only the localizer's starting point before its global search.
        region: ``(x, y, radius)`` of a Relocalize, if given.
        anchor: the robot's odometry pose at ``stamp_ns`` when the request was received.
    """

    kind: Literal["initialpose", "relocalize"]
    map_id: str
    stamp_ns: int
    received_ns: int
    pose: FloatArray
    region: tuple[float, float, float] | None = None
    anchor: FloatArray | None = None

    def describe(self) -> str:
        """``map M`` or ``map M within R m of (X, Y)``, for messages."""
        if self.region is None:
            return f"map {self.map_id!r}"
        x, y, r = self.region
        return f"map {self.map_id!r} within {r:g} m of ({x:g}, {y:g})"


EventSpec = tuple[Level, str, str]
"""An Event to publish: level, code, message."""


class Episode:
    """One relocalization of one robot, from its start to the result that ends it.

    Args:
        reason: why it started, for the ``relocalizing`` message.
    """

    def __init__(self, reason: str) -> None:
        self.reason = reason
        self.announced = False
        self.ambiguous = False
        self.updates = 0

    def start(self) -> list[EventSpec]:
        """The ``relocalizing`` event, the first time it is asked for."""
        if self.announced:
            return []
        self.announced = True
        return [("info", EventCode.RELOCALIZING, f"relocalizing: {self.reason}")]

    def follow(self, result: LocalizeResult) -> tuple[list[EventSpec], bool]:
        """The events of one result of the episode, and whether the episode ended with it."""
        events = self.start()
        self.updates += 1
        hyps = result.hypotheses
        if len(hyps) > 1 and not self.ambiguous:
            self.ambiguous = True
            named = ", ".join(
                f"({h.pose[0]:.2f}, {h.pose[1]:.2f}, {h.pose[2]:.2f}) score {h.score:.2f}"
                for h in hyps[:_NAMED]
            )
            events.append(
                (
                    "warning",
                    EventCode.AMBIGUOUS,
                    f"{len(hyps)} places fit the scan about equally: {named}; following them "
                    "with odometry and the next scans until one wins (status lost meanwhile)",
                )
            )
        if result.status == "corrected" and not hyps:
            x, y, theta = (float(v) for v in result.pose)
            events.append(
                (
                    "info",
                    EventCode.RELOCALIZED,
                    f"relocalized at ({x:.3f}, {y:.3f}, {theta:.3f}) after {self.updates} "
                    f"scan(s){' (was ambiguous)' if self.ambiguous else ''}",
                )
            )
            return events, True
        return events, False


def placed_during(episode: Episode | None, placed: Request) -> list[EventSpec]:
    """The ``relocalized`` event of an episode that an InitialPose ends (the operator placed the
    robot while it was being relocalized: an operator's Relocalize, or the one a restart seeds
    from a pose too old to resume from), so that every ``relocalizing`` has its end."""
    if episode is None or not episode.announced:
        return []
    x, y, theta = (float(v) for v in placed.pose)
    return [
        (
            "info",
            EventCode.RELOCALIZED,
            f"relocalization ended by an initial pose: placed at ({x:.3f}, {y:.3f}, "
            f"{theta:.3f}) on map {placed.map_id!r} after {episode.updates} scan(s)",
        )
    ]


def wire_hypotheses(result: LocalizeResult) -> tuple[Hypothesis, ...] | None:
    """``PoseEstimate.hypotheses`` of a result: ``None`` when it has none."""
    if not result.hypotheses:
        return None
    return tuple(
        Hypothesis(
            x=float(h.pose[0]),
            y=float(h.pose[1]),
            theta=float(h.pose[2]),
            score=_unit(float(h.score)),
        )
        for h in result.hypotheses
    )


def _unit(score: float) -> float:
    return min(max(score, 0.0), 1.0) if math.isfinite(score) else 0.0


def searching(relocalizing: bool, region: tuple[float, float, float] | None) -> str:
    """What a lost robot's localizer does next, for its Event: a relocalization in a circle (an
    operator's ``--near``) searches the whole map if nothing fits there
    (:attr:`rlutf.relocalize.FollowSettings.widen_after`)."""
    if not relocalizing:
        return "searching wider at the next scan"
    if region is None:
        return "relocalizing on the whole map"
    x, y, radius = region
    return f"relocalizing within {radius:g} m of ({x:g}, {y:g}); if not there, on the whole map"


def unfit(result: LocalizeResult, distance: float, min_fit: float) -> str:
    """Why a pose is lost, with the share of the returns that fit and the share needed."""
    needed = result.fit_needed if math.isfinite(result.fit_needed) else min_fit
    fit = result.fit if math.isfinite(result.fit) else 0.0
    digits = 0  # enough digits that the two shares never read the same
    while digits < 3 and round(100 * fit, digits) >= round(100 * needed, digits):
        digits += 1
    shares = (
        f"only {100 * fit:.{digits}f} % of its returns lie within {distance:g} m of the map at "
        f"the best pose, under the {100 * needed:.{digits}f} % needed"
    )
    if needed > min_fit:
        return (
            f"the scan fits the map worse than this robot's scans usually do: {shares} (its "
            f"usual share less a margin; never under {100 * min_fit:.0f} %); "
        )
    return f"the scan does not fit the map: {shares}; "
