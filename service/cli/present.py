"""How the command line shows things to a person: aligned tables, angles in degrees, lengths in
centimetres, ages as seconds or minutes, Events as one line each.

``--json`` output is not made here: the commands print the wire messages as they are.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from schemas import Event, EventCode, Health, PoseEstimate, RobotState, WaitingRobot
from service.keys import printable
from service.live.robots import NO_RETURNS, NO_SCAN_YET, one_sigma

if TYPE_CHECKING:
    from rich.console import Console


def console(stderr: bool = False) -> Console:
    """A rich console; tables keep their columns (and robot ids) when the output is not a
    terminal (a pipe, a file, a CI log), where rich would squeeze them into 80 columns."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    chosen = stream.isatty() or "COLUMNS" in os.environ  # else 132 columns
    return Console(stderr=stderr, width=None if chosen else 132)


#: A robot with no pose published for longer than this is shown as silent, seconds.
SILENT_AFTER_S = 5.0

#: Shown under the table when robots wait for an initial pose.
WAITING_HINT = (
    "waiting: the robot sends scans but has no pose yet; give it one with "
    "`rlutf initialpose ROBOT --map ID --pose X,Y,THETA`"
)
NO_SCAN_HINT = (
    "no scan yet: the robot has an initial pose (or a Relocalize) and has sent no scan since; "
    "its next scan gives its first pose (is it sending scans? `rlutf events ROBOT`)"
)
NO_RETURNS_HINT = (
    "no returns: the robot's scans have too few returns to compare, so no pose goes out (a "
    "blocked or failing lidar, or range limits that leave nothing? `rlutf events ROBOT`)"
)
NO_MAP_HINT = (
    "no map: the robot's map is in no storage (its initial pose or scans wait for it); "
    "`rlutf map list` shows the stored maps, `rlutf map put FILE --id ID` stores one"
)
CLOCK_HINT = (
    "clock ahead: the robot's scans and odometry are stamped too far ahead of the service's "
    "clock (max_stamp_ahead_s), so each is refused; synchronise its clock (chrony, NTP) with the "
    "service's host (`rlutf events ROBOT`)"
)
#: How each waiting reason reads in the status column, and its hint.
_WAITS = {
    NO_SCAN_YET: ("no scan yet", NO_SCAN_HINT),
    NO_RETURNS: ("no returns", NO_RETURNS_HINT),
    EventCode.MAP_NOT_FOUND: ("no map", NO_MAP_HINT),
    EventCode.STAMP_REJECTED: ("clock ahead", CLOCK_HINT),
}


def table(header: Sequence[str], rows: Iterable[Sequence[str]], right: set[int]) -> str:
    """A plain-text table: columns aligned, those in ``right`` (numbers) to the right."""
    body = [list(header), *(list(r) for r in rows)]
    widths = [max(len(r[i]) for r in body) for i in range(len(header))]
    return "\n".join(
        "  ".join(
            cell.rjust(widths[i]) if i in right else cell.ljust(widths[i])
            for i, cell in enumerate(row)
        ).rstrip()
        for row in body
    )


def num(value: float | None, digits: int) -> str:
    """``value`` with ``digits`` decimals; ``-`` for none."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def degrees(radians: float | None, digits: int = 1) -> str:
    """An angle in degrees."""
    return "-" if radians is None else num(math.degrees(radians), digits)


def centimetres(metres: float | None) -> str:
    """A length in centimetres, one decimal under 10 cm."""
    if metres is None or not math.isfinite(metres):
        return "-"
    cm = 100 * metres
    return f"{cm:.1f}" if cm < 10 else f"{cm:.0f}"


def age(seconds: float | None) -> str:
    """An age: ``0.04 s``, ``12 s``, ``3 min 20 s``, ``2 h 05 min``."""
    if seconds is None or not math.isfinite(seconds):
        return "-"
    if seconds < 10:
        return f"{seconds:.2f} s"
    if seconds < 100:
        return f"{seconds:.0f} s"
    whole = round(seconds)
    if whole < 3600:
        return f"{whole // 60} min {whole % 60:02d} s"
    return f"{whole // 3600} h {whole % 3600 // 60:02d} min"


def status_of(state: RobotState, silent_after: float = SILENT_AFTER_S) -> str:
    """The robot's status, ``silent (...)`` once no pose has come for ``silent_after`` s."""
    if state.refused == EventCode.STAMP_REJECTED:
        return f"clock ahead ({state.status})"
    if state.age_s is not None and state.age_s > silent_after:
        return f"silent ({state.status})"
    return state.status


ROBOT_COLUMNS = ("robot", "map", "status", "x m", "y m", "θ °", "±xy cm", "±θ °", "age")


def robots_table(
    states: Iterable[RobotState],
    waiting: Iterable[WaitingRobot] = (),
    silent_after: float = SILENT_AFTER_S,
) -> str:
    """``rlutf robots``: one line per robot, then the robots waiting for an initial pose."""
    states = list(states)
    rows = [
        [
            s.robot_id,
            s.map_id,
            status_of(s, silent_after),
            num(s.x, 3),
            num(s.y, 3),
            degrees(s.theta),
            centimetres(s.sigma_xy_m),
            degrees(s.sigma_theta_rad, 2),
            age(s.age_s),
            num(s.latency_ms, 1),
            s.owner,
        ]
        for s in states
    ]
    waits = list(waiting)
    rows += [
        [w.robot_id, w.map_id or "-", _wait(w)[0], *["-"] * 5, age(w.age_s), "-", w.owner]
        for w in waits
    ]
    text = table([*ROBOT_COLUMNS, "latency ms", "owner"], rows, {3, 4, 5, 6, 7, 8, 9})
    shown = {_wait(w)[1] for w in waits} | {CLOCK_HINT for s in states if s.refused}
    known = (WAITING_HINT, NO_MAP_HINT, NO_SCAN_HINT, NO_RETURNS_HINT, CLOCK_HINT)
    hints = [h for h in known if h in shown]
    return "\n\n".join([text, *hints])


def _wait(w: WaitingRobot) -> tuple[str, str]:
    """A waiting robot's status as shown, and the hint that explains it."""
    return _WAITS.get(w.reason, ("waiting", WAITING_HINT))


def poses_table(poses: Iterable[PoseEstimate], now_ns: int | None = None) -> str:
    """``rlutf pose``: one line per robot; age is now minus the scan's stamp."""
    now = time.time_ns() if now_ns is None else now_ns
    rows = []
    for p in poses:
        sxy, sth = one_sigma(p.covariance)
        rows.append(
            [
                p.robot_id,
                p.map_id,
                p.status,
                num(p.x, 3),
                num(p.y, 3),
                degrees(p.theta),
                centimetres(sxy),
                degrees(sth, 2),
                age(max(now - p.stamp_ns, 0) / 1e9),
                num(p.discrepancy, 4),
            ]
        )
    return table([*ROBOT_COLUMNS, "discrepancy"], rows, {3, 4, 5, 6, 7, 8, 9})


def health_table(healths: Iterable[Health]) -> str:
    """``rlutf health``: one line per instance."""
    header = (
        "instance",
        "ready",
        "up",
        "robots",
        "received",
        "rejected",
        "processed",
        "dropped",
        "p50 ms",
        "p99 ms",
        "max ms",
    )
    rows = []
    for h in healths:
        ready = getattr(h, "ready", None)
        if ready is None:
            ready = (h.model_extra or {}).get("ready")
        name = h.instance
        processes = h.extra.get("processes") if h.extra.get("host") is True else None
        if isinstance(processes, list):  # a host: its processes' rows follow, added up here
            name = f"{name} (host: {len(processes)} processes added up; latency: the slowest)"
        rows.append(
            [
                name,
                "-" if ready is None else ("yes" if ready else "no"),
                age(h.uptime_s),
                str(h.robots),
                str(h.received),
                str(h.rejected),
                str(h.processed),
                str(h.dropped),
                num(h.latency_ms.p50, 1),
                num(h.latency_ms.p99, 1),
                num(h.latency_ms.max, 1),
            ]
        )
    return table(header, rows, set(range(2, len(header))))


#: Health figures that mean an instance is losing what it should keep: figure, what it says.
_LOSSES = (
    (
        "recorder_unrecorded",
        "messages not recorded: the log folder could not be written (a full disk? the "
        "recording_failed Event says why)",
    ),
    ("recorder_overflow", "messages not recorded: the recorder's queue was full"),
    ("state_write_errors", "pose-state writes failed: a restart may not resume its robots"),
)
#: Figures of :data:`_LOSSES` that matter only while a flag of the same Health says so: failed
#: pose-state writes are made good by the next one that works (recorded messages lost are not).
_WHILE = {"state_write_errors": "state_write_failing"}


def health_problems(healths: Iterable[Health]) -> list[str]:
    """``rlutf health``: a line for each instance losing its log or its pose state (a host's
    figures are its processes', named on their own lines)."""
    lines = []
    for h in healths:
        if h.extra.get("host") is True:
            continue
        for figure, says in _LOSSES:
            n = h.extra.get(figure)
            if h.extra.get(_WHILE.get(figure, ""), True) is False:
                continue  # failed before, written since
            if isinstance(n, int) and n > 0:
                lines.append(f"{h.instance}: {n:,} {says}")
    return lines


def event_line(robot: str | None, ev: Event) -> str:
    """One Event as a line: local time, level, robot (``-``: service-wide, with the Event's key),
    code and message; control characters escaped (what comes off the bus, a key or an Event put
    by any client, must not drive the operator's terminal: clear it, recolour it, hide a
    line)."""
    clock = time.strftime("%H:%M:%S", time.localtime(ev.stamp_ns / 1e9))
    millis = ev.stamp_ns // 1_000_000 % 1000
    code = ev.code if robot else f"{ev.code} ({ev.key})"  # service-wide: which map or key
    text = ev.message if ev.message.startswith(f"{ev.code}:") else f"{code}: {ev.message}"
    line = f"{clock}.{millis:03d}  {ev.level:<7}  {robot or '-'}  {text}"
    return printable(line, limit=len(line))


def pose_line(p: PoseEstimate) -> str:
    """One pose as a sentence."""
    sxy, sth = one_sigma(p.covariance)
    spread = "" if sxy is None else f" ± {centimetres(sxy)} cm, {degrees(sth, 2)}°"
    return (
        f"{p.robot_id} on {p.map_id}: {p.status} at x {p.x:.3f} m, y {p.y:.3f} m, "
        f"θ {degrees(p.theta)}°{spread}"
    )


def unfinished(
    command: str, paths: Sequence[Path], files: Sequence[Path], what: str
) -> tuple[int, int]:
    """Name the unfinished logs (``.mcap.part``) of the folders among ``paths``, which the log
    tools do not read, unless a copy recovered from one is among ``files`` (``rlutf log
    recover`` names it as the log's final name); returns how many a crash left and how many are
    being recorded."""
    from service.logs.partfile import left_unfinished, part_message
    from service.logs.runs import unfinished_logs

    given = {f.name for f in files}
    crashed = recording = 0
    for part in unfinished_logs(paths):
        if part.name.removesuffix(".part") in given:
            continue  # recovered, and the copy is read
        left = left_unfinished(part)
        crashed += left
        recording += not left
        more = (
            f"; or recover every such log of the folder with rlutf log recover "
            f"{part.parent}/ RECOVERED/ and give RECOVERED/ too"
            if left
            else ""
        )
        print(f"rlutf {command}: {what}: {part_message(part)}{more}", file=sys.stderr)
    return crashed, recording
