"""Bounded work per input, decided before the work; and a robot's state kept when an update fails.

The schema accepts any finite number, and some finite numbers are of no use to a localizer while
they cost it without bound: a scan whose ranges are 1e5 m makes the wide search step its heading
by a millionth of a radian, an ``angle_increment`` of 5e-324 puts every beam on one line, a pose
at 1e308 overflows the first subtraction. :class:`Limits` (``limits.*`` in the settings) says what
the service accepts; :func:`check_input` names the first field over a limit, and the engine turns
it into an Event ``invalid_message`` before anything of the robot's state is touched.

Ranges are not rejected but bounded: a range longer than any wall of the robot's map can be (the
map's diagonal plus the sensor's offset) or than ``limits.max_range`` carries no information, so
:func:`usable_scan` makes it no return and caps ``range_max`` there before any search.

Everything here runs inside :class:`service.engine.FleetEngine`, which the live service and replay
share, so a replay rejects and caps exactly what the live service did.

:class:`Snapshot` holds what one input may change of a robot, so that an update that raises (a
bug, or a number no limit foresaw) is undone: the engine restores the robot as it was and
publishes an Event ``internal_error`` instead of a traceback.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, Final, Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rlutf.map import Map as World
from rlutf.scan import Scan
from schemas import MAX_BEAMS, EventCode, InitialPose, LaserScan, Odometry, Relocalize
from service.keys import Keys

if TYPE_CHECKING:
    from service.maphealth import Handed

Message = LaserScan | Odometry | InitialPose | Relocalize
OutKind = Literal["pose", "event", "need_map", "skipped", "rejected", "evidence"]

_TWO_PI: Final = 2.0 * math.pi
#: Longest duration a setting in seconds may hold: the service waits on these (a lock's timed
#: wait fails past ``threading.TIMEOUT_MAX``, about 9.2e9 s) and counts them in nanoseconds
#: (``int(1e308 * 1e9)`` overflows); 1e9 s is 31 years, as the commands' ``--timeout``.
MAX_SECONDS: Final = 1e9
#: A setting in seconds: finite, at most :data:`MAX_SECONDS` (its own ``Field`` adds its floor).
Seconds = Annotated[float, Field(le=MAX_SECONDS)]
#: Metres added to the map's diagonal (and the sensor's offset) beyond which a range is no return.
_REACH_MARGIN_M: Final = 1.0
#: The attribute of :class:`rlutf.localizer.Localizer` holding a relocalization under way, the
#: one part of its state an update changes in place (the rest it reassigns).
_RELOCALIZATION: Final = "_follower"
#: The types of a robot's fields that a snapshot copies (an update changes them in place).
_COPIED: Final = (list, dict)


@dataclass(frozen=True)
class Outbound:
    """Something the engine wants published (:mod:`service.engine` exports it).

    Attributes:
        kind: ``pose`` (a PoseEstimate for ``key``), ``event`` (an Event for ``key``),
            ``need_map`` (``map_id`` is wanted from the store; nothing is published),
            ``skipped`` (a scan was not turned into a pose; counted, nothing is published) or
            ``rejected`` (an input over a limit of :mod:`service.guard`; counted, nothing is
            published: its Event, rate-limited, is a separate ``event``) or ``evidence`` (map
            health evidence handed on, ``FleetEngine.hand_over``).
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


class Engine(Protocol):
    """What :func:`guarded` needs of :class:`service.engine.FleetEngine`."""

    keys: Keys
    limits: Limits

    def _handle(self, robot: Any, message: Message, received_ns: int) -> list[Outbound]: ...

    def _event(
        self,
        robot: Any,
        now_ns: int,
        level: Any,
        code: str,
        key: str,
        message: str,
        limited: bool = True,
    ) -> list[Outbound]: ...


def guarded(engine: Engine, robot: Any, message: Message, received_ns: int) -> list[Outbound]:
    """Apply one input of a robot with ``engine``, within the limits and undone if it raises.

    An input over a limit (:func:`check_input`) changes nothing and gives an Event
    ``invalid_message``; an update that raises is undone (the robot's state is as before the
    input, :class:`Snapshot`) and gives an Event ``internal_error``.
    """
    problem = check_input(message, engine.limits)
    if problem is not None:
        kind = kind_of(message)
        key = engine.keys.robot(robot.robot_id, kind)
        # An operator's request is answered each time: `rlutf initialpose` waits for the Event
        # (a robot's scans and odometry come too often for that: held back per interval).
        request = isinstance(message, InitialPose | Relocalize)
        code = EventCode.INVALID_MESSAGE
        return [
            Outbound("rejected", key, b"", message.stamp_ns, robot.robot_id),
            *engine._event(robot, received_ns, "error", code, key, problem, limited=not request),
        ]
    # Odometry only appends to the robot's readings, all or nothing (FleetEngine._add_odometry):
    # nothing to put back, and no snapshot to take for half of the inputs.
    saved = None if isinstance(message, Odometry) else Snapshot(robot)
    try:
        return engine._handle(robot, message, received_ns)
    except Exception as err:  # one robot's failure never reaches the others or the caller
        if saved is not None:
            saved.restore(robot)
        kind = kind_of(message)
        key = engine.keys.robot(robot.robot_id, kind)
        text = (
            f"{kind} {message.stamp_ns} not applied: {type(err).__name__}: {str(err)[:200]}"
            f"{where(err)}; the robot's state is as before it"
        )
        return engine._event(robot, received_ns, "error", EventCode.INTERNAL_ERROR, key, text)


def kind_of(message: Message) -> str:
    """The key leaf of an input: ``scan``, ``odom``, ``initialpose`` or ``relocalize``."""
    if isinstance(message, LaserScan):
        return "scan"
    if isinstance(message, Odometry):
        return "odom"
    return "initialpose" if isinstance(message, InitialPose) else "relocalize"


def where(err: BaseException) -> str:
    """`` at DIR/FILE:LINE`` of the innermost frame of ``err``'s traceback, for its Event."""
    tb = err.__traceback__
    if tb is None:
        return ""
    while tb.tb_next is not None:
        tb = tb.tb_next
    path = tb.tb_frame.f_code.co_filename.replace("\\", "/")
    return f" at {'/'.join(path.split('/')[-2:])}:{tb.tb_lineno}"


class Limits(BaseModel):
    """What the service accepts beyond the schema (``limits.*``, ``RLUTF_LIMITS__*``).

    The defaults leave every real robot's input alone (a 0.05 degree scanner, odometry that has
    run for years, a sensor on a truck) and stop what would cost a localizer without bound.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_beams: int = Field(
        MAX_BEAMS, ge=1, le=MAX_BEAMS, description="Most beams in one LaserScan."
    )
    min_angle_increment: float = Field(
        1e-4,
        gt=0,
        description="Smallest |angle_increment| of a LaserScan, radians (a 0.05 degree "
        "scanner's is 8.7e-4).",
    )
    max_sweep: float = Field(
        _TWO_PI * 1.01,
        gt=0,
        description="Largest angle between a scan's first and last beams, radians (a little "
        "over a full turn).",
    )
    max_range: float = Field(
        1000.0,
        gt=0,
        description="Longest usable range, metres: longer ranges (and longer than the robot's "
        "map can hold) are no return, and range_max is capped there.",
    )
    max_coordinate: float = Field(
        1e6,
        gt=0,
        description="Largest |x| or |y| of odometry, poses and regions, and largest region "
        "radius, metres.",
    )
    max_angle: float = Field(
        1e6,
        gt=0,
        description="Largest |theta| of odometry and poses and |angle_min| of a scan, radians "
        "(odometry headings may be unwrapped).",
    )
    max_sensor_offset: float = Field(
        100.0, gt=0, description="Largest |x| or |y| of a scan's sensor_offset, metres."
    )


def _over(name: str, value: float, limit: float, setting: str, unit: str) -> str | None:
    if abs(value) <= limit:
        return None
    return (
        f"{name} {value!r} is beyond what the service accepts: |{name}| <= {limit:g} {unit} "
        f"({setting})"
    )


def check_input(message: Message, limits: Limits) -> str | None:
    """The first field of ``message`` over a limit, as an Event message; ``None`` if none is.

    Every input of every robot passes here: the numbers are compared first, and a message is
    written only for an input over a limit.

    Args:
        message: a validated input.
        limits: what the service accepts.
    """
    lim = limits
    if isinstance(message, LaserScan):
        n = len(message.ranges)
        inc = message.angle_increment
        off = message.sensor_offset
        if (
            n <= lim.max_beams
            and abs(inc) >= lim.min_angle_increment
            and abs(inc) * (n - 1) <= lim.max_sweep
            and abs(message.angle_min) <= lim.max_angle
            and abs(off.x) <= lim.max_sensor_offset
            and abs(off.y) <= lim.max_sensor_offset
            and abs(off.theta) <= lim.max_angle
        ):
            return None
        return _scan_over(message, lim)
    if isinstance(message, Odometry | InitialPose):
        coordinate, angle = lim.max_coordinate, lim.max_angle
        if (
            abs(message.x) <= coordinate
            and abs(message.y) <= coordinate
            and abs(message.theta) <= angle
        ):
            return None
        kind = type(message).__name__
        checks = [
            _over(f"{kind}.x", message.x, coordinate, "limits.max_coordinate", "m"),
            _over(f"{kind}.y", message.y, coordinate, "limits.max_coordinate", "m"),
            _over(f"{kind}.theta", message.theta, angle, "limits.max_angle", "rad"),
        ]
        return next((c for c in checks if c is not None), None)
    region = message.region
    if region is None:
        return None
    kind = type(message).__name__
    checks = [
        _over(f"{kind}.region.{name}", value, lim.max_coordinate, "limits.max_coordinate", "m")
        for name, value in (("x", region.x), ("y", region.y), ("radius", region.radius))
    ]
    return next((c for c in checks if c is not None), None)


def _scan_over(message: LaserScan, lim: Limits) -> str | None:
    """The first field of a scan over a limit, as an Event message (:func:`check_input`)."""
    kind = type(message).__name__
    n = len(message.ranges)
    if n > lim.max_beams:
        return (
            f"{kind}.ranges has {n} beams; at most {lim.max_beams} are accepted (limits.max_beams)"
        )
    inc = message.angle_increment
    if abs(inc) < lim.min_angle_increment:
        return (
            f"{kind}.angle_increment {inc!r} is below the smallest usable |increment| "
            f"{lim.min_angle_increment:g} rad (limits.min_angle_increment)"
        )
    sweep = abs(inc) * (n - 1)
    if sweep > lim.max_sweep:
        return (
            f"{kind}.angle_increment {inc!r} times {n - 1} spans {sweep:g} rad; at most "
            f"{lim.max_sweep:g} rad are accepted (limits.max_sweep)"
        )
    off = message.sensor_offset
    checks = [
        _over(f"{kind}.angle_min", message.angle_min, lim.max_angle, "limits.max_angle", "rad"),
        _over(
            f"{kind}.sensor_offset.x", off.x, lim.max_sensor_offset, "limits.max_sensor_offset", "m"
        ),
        _over(
            f"{kind}.sensor_offset.y", off.y, lim.max_sensor_offset, "limits.max_sensor_offset", "m"
        ),
        _over(f"{kind}.sensor_offset.theta", off.theta, lim.max_angle, "limits.max_angle", "rad"),
    ]
    return next((c for c in checks if c is not None), None)


def reach(world: World, sensor_offset: tuple[float, float], limits: Limits) -> float:
    """The longest range that can hit a wall of ``world``, metres (capped by ``max_range``).

    A sensor inside the map sees no wall farther than the map's diagonal; a robot the localizer
    keeps on the map has its sensor within ``|sensor_offset|`` of it.
    """
    x0, y0, x1, y1 = world.bounds
    diagonal = math.hypot(x1 - x0, y1 - y0)
    return min(limits.max_range, diagonal + math.hypot(*sensor_offset) + _REACH_MARGIN_M)


def usable_scan(msg: LaserScan, world: World, limits: Limits) -> Scan:
    """The scan of ``msg`` with every range beyond :func:`reach` made no return.

    ``range_max`` is capped at the reach too, so no ray is cast and no search step is chosen for
    a distance no wall of the map can be at. A scan whose ``range_min`` is beyond the reach has
    no return at all.
    """
    off = msg.sensor_offset
    far = reach(world, (off.x, off.y), limits)
    ranges = np.array(msg.ranges, dtype=np.float64)  # None (no return) becomes NaN
    range_min, range_max = msg.range_min, msg.range_max
    if range_max > far:
        ranges[ranges > far] = np.nan
        if range_min >= far:
            range_min = 0.0
            ranges[:] = np.nan
        range_max = far
    return Scan.create(
        ranges,
        msg.angle_min,
        msg.angle_increment,
        range_min,
        range_max,
        (off.x, off.y, off.theta),
    )


def region_on(
    region: tuple[float, float, float] | None, world: World
) -> tuple[float, float, float] | None:
    """A Relocalize region as searched: ``None`` (the whole map) when it holds the whole map.

    The search over a region costs in proportion to the region's area; one larger than the map
    is the map.
    """
    if region is None:
        return None
    x, y, radius = region
    x0, y0, x1, y1 = world.bounds
    farthest = max(math.hypot(cx - x, cy - y) for cx in (x0, x1) for cy in (y0, y1))
    return None if radius >= farthest else region


class Snapshot:
    """What one input may change of a robot, to put back if its update raises.

    The engine's per-robot record is copied field by field (its lists and dicts copied), the
    localizer's attributes likewise, with its random generator's state; a relocalization under
    way is deep-copied (sharing the map). Taken before every input: a few microseconds, more only
    while the robot relocalizes.
    """

    def __init__(self, robot: Any) -> None:
        fields = dict(vars(robot))
        for name, value in fields.items():
            if isinstance(value, _COPIED):
                fields[name] = value.copy()
        self.fields = fields
        episode = robot.episode
        self.episode = None if episode is None else copy.copy(episode)
        loc = robot.localizer
        self.localizer = loc
        self.loc_fields: dict[str, Any] = {}
        self.generators: dict[str, Any] = {}
        if loc is None:
            return
        loc_fields = self.loc_fields = dict(vars(loc))
        for name, value in loc_fields.items():
            if isinstance(value, np.random.Generator):
                self.generators[name] = value.bit_generator.state
        following = loc_fields.get(_RELOCALIZATION)
        if following is not None:  # changed in place: copied
            loc_fields[_RELOCALIZATION] = copy.deepcopy(
                following, {id(following.world): following.world}
            )

    def restore(self, robot: Any) -> None:
        """Put the robot back as it was when the snapshot was taken."""
        vars(robot).update(self.fields)
        robot.episode = self.episode
        loc = self.localizer
        if loc is None:
            return
        vars(loc).clear()
        vars(loc).update(self.loc_fields)
        for name, state in self.generators.items():
            getattr(loc, name).bit_generator.state = state
