"""Audit: recorded poses against the poses a replay recomputed from the same inputs.

Poses are matched per robot by the stamp of the scan they answer (in order among equal
stamps). Per robot the audit reports the translation and heading deviations (max and RMS),
how many payloads are byte-identical, and the poses present on one side only:

* ``missing``: recorded but not recomputed: always a failure;
* ``extra``: recomputed but not recorded, before the robot's last recorded pose: a failure;
* ``unverified``: recomputed after the robot's last recorded pose, for an input received in the
  log's last :data:`TAIL_NS`: the log ends before them (a recovered crash log loses its last
  second), reported but not a failure unless ``strict``; one answering an input received
  earlier had time to be recorded, and is ``extra``;
* ``after_gap``: recorded poses stamped after a recording gap began (Event
  ``recording_resumed``: the recorder could not write, a full disk; or ``recorder_overflow``:
  its queue was full and messages were lost): the log lacks the gap's
  inputs, so the replay cannot recompute them as they were; reported, not compared, and not a
  failure unless ``strict``.

A robot fails when a deviation exceeds its tolerance, a status differs, any other field of a
matched pair differs (``map_id``, the covariance, the quality fields, the hypotheses, a key on
one side only; numbers by more than the translation tolerance), or poses are missing or extra.
Where the log holds no poses at all there is nothing to audit.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from rich.console import Console
from rich.table import Table

from service.logs.posematch import PoseMatch, PoseRecord, Tally
from service.logs.runs import LogRun

DEFAULT_TOLERANCE = 1e-9

TAIL_NS = 30_000_000_000
"""How long before a log's end an input may have been received and its pose still not be in
the log. A pose is published a moment after its scan, seconds after it under overload; a log
recovered after a crash loses its last second or so (the recorder flushes every second); 30 s,
as long as a map build waits for a scan's pose. Before, every pose recomputed after a robot's
last recorded one was "unverified", however early: a log with all of one robot's poses
deleted (or all from some hour on) audited as passed."""
UNREADABLE = "unreadable"
"""A run's result when one of its files could not be read."""
INCOMPLETE = "incomplete"
"""A run's result when records of it were not read (:mod:`service.logs.completeness`): no
alarm, and no pass either."""


@dataclass(frozen=True)
class RobotAudit:
    """The comparison for one robot (deviations in metres and radians)."""

    robot: str
    matched: int
    identical: int
    missing: int
    extra: int
    unverified: int
    status_differs: int
    max_translation: float
    rms_translation: float
    max_heading: float
    rms_heading: float
    after_gap: int = 0
    fields: tuple[tuple[str, int, float], ...] = ()
    """Fields other than the pose and status that differ: (name, pairs, largest deviation)."""

    def fields_past(self, tolerance_m: float) -> list[tuple[str, int, float]]:
        """The fields that differ by more than ``tolerance_m`` (infinity: not a number)."""
        return [f for f in self.fields if f[2] > tolerance_m]

    def passed(self, tolerance_m: float, tolerance_rad: float, strict: bool = False) -> bool:
        """Whether the robot's recorded poses are reproduced within the tolerances."""
        return (
            self.max_translation <= tolerance_m
            and self.max_heading <= tolerance_rad
            and self.missing == 0
            and self.extra == 0
            and self.status_differs == 0
            and not self.fields_past(tolerance_m)
            and (not strict or self.unverified == self.after_gap == 0)
        )


def _robot_audit(robot: str, r: Tally, tail_from: int | None) -> RobotAudit:
    last = r.last_recorded
    left = [p for q in r.recomputed.values() for p in q]
    unverified = sum(
        1
        for p in left
        if (last is None or p.stamp_ns > last) and (tail_from is None or p.log_time_ns >= tail_from)
    )

    def rms(total: float) -> float:
        return math.sqrt(total / r.matched) if r.matched else 0.0

    return RobotAudit(
        robot=robot,
        matched=r.matched,
        identical=r.identical,
        missing=sum(len(q) for q in r.recorded.values()),
        extra=len(left) - unverified,
        unverified=unverified,
        status_differs=r.status_differs,
        max_translation=r.max_translation,
        rms_translation=rms(r.sum_translation_sq),
        max_heading=r.max_heading,
        rms_heading=rms(r.sum_heading_sq),
        after_gap=r.after_gap,
        fields=tuple((name, n, d) for name, (n, d) in sorted(r.fields.items())),
    )


def audit_match(match: PoseMatch) -> list[RobotAudit]:
    """The audit of the poses fed to ``match`` (each robot's, sorted by robot); empty when no
    recorded pose was fed (nothing to audit)."""
    if not match.recorded_total:
        return []
    # Where the recorder had a gap, poses queued when it began were lost too: the old rule.
    known = match.end_ns is not None and match.gap_ns is None
    tail_from = match.end_ns - TAIL_NS if known and match.end_ns is not None else None
    return [_robot_audit(robot, match.robots[robot], tail_from) for robot in sorted(match.robots)]


def audit(
    recorded: Mapping[str, Sequence[PoseRecord]],
    recomputed: Mapping[str, Sequence[PoseRecord]],
    gap_ns: int | None = None,
) -> list[RobotAudit]:
    """Compare per robot, up to ``gap_ns`` (a recording gap's start) if given; empty when
    ``recorded`` holds no poses (nothing to audit)."""
    match = PoseMatch(gap_ns)
    for robot in sorted(set(recorded) | set(recomputed)):
        match.tally(robot)  # a robot with no pose on either side is still reported
        for rec in recorded.get(robot, ()):
            match.recorded(rec)
        for new in recomputed.get(robot, ()):
            match.recomputed(new)
    return audit_match(match)


def gap_note(audits: Sequence[RobotAudit], gap_ns: int | None) -> str | None:
    """What an audit up to a recording gap left out, if anything."""
    left = sum(a.after_gap for a in audits)
    if not left or gap_ns is None:
        return None
    began = datetime.fromtimestamp(gap_ns / 1e9, UTC).isoformat(timespec="milliseconds")
    return (
        f"{left} recorded poses after a recording gap (from {began}, Event recording_resumed or "
        "recorder_overflow) not audited: the log lacks the gap's inputs"
    )


def all_passed(
    audits: Sequence[RobotAudit], tolerance_m: float, tolerance_rad: float, strict: bool = False
) -> bool:
    """Whether every robot passed."""
    return all(a.passed(tolerance_m, tolerance_rad, strict) for a in audits)


def render(
    audits: Sequence[RobotAudit],
    tolerance_m: float,
    tolerance_rad: float,
    console: Console,
    strict: bool = False,
    heading: str = "Audit",
    incomplete: Collection[str] = (),
) -> None:
    """Print the per-robot table, titled ``heading`` (e.g. which run); the robots
    ``incomplete`` (whose records were not all read) are marked so, whatever their poses."""
    table = Table(
        title=f"{heading}: recorded vs recomputed poses (tolerance {tolerance_m:g} m, "
        f"{tolerance_rad:g} rad)"
    )
    for name in (
        "robot",
        "matched",
        "identical",
        "missing",
        "extra",
        "unverified",
        "status differs",
        "max dxy [m]",
        "rms dxy [m]",
        "max dtheta [rad]",
        "rms dtheta [rad]",
        "result",
    ):
        table.add_column(name, justify="left" if name == "robot" else "right")
    table.columns[-1].min_width = len("incomplete") if incomplete else None
    for a in audits:
        ok = a.passed(tolerance_m, tolerance_rad, strict)
        result = "[green]ok[/green]" if ok else "[bold red]FAIL[/bold red]"
        table.add_row(
            a.robot,
            str(a.matched),
            str(a.identical),
            str(a.missing),
            str(a.extra),
            str(a.unverified),
            str(a.status_differs),
            f"{a.max_translation:.3g}",
            f"{a.rms_translation:.3g}",
            f"{a.max_heading:.3g}",
            f"{a.rms_heading:.3g}",
            "[yellow]incomplete[/yellow]" if a.robot in incomplete else result,
        )
    console.print(table)
    for a in audits:
        past = a.fields_past(tolerance_m)
        if past:
            said = ", ".join(
                f"{name} in {n} pose(s)" + (f" (by up to {d:.3g})" if math.isfinite(d) else "")
                for name, n, d in past
            )
            console.print(f"[red]{a.robot}: recorded poses differ from the recomputed ones in "
                          f"{said}[/red]", soft_wrap=True)  # fmt: skip


@dataclass(frozen=True)
class RunVerdict:
    """One run's line in the final summary of an audit over several runs.

    Attributes:
        label: how the run is named (short id and instance).
        started: when the run started (UTC, ISO 8601), or ``-``.
        files: its files.
        robots: robots audited.
        poses: recorded poses compared.
        result: ``passed``, ``FAILED``, ``nothing to audit``, :data:`INCOMPLETE` or
            :data:`UNREADABLE`.
        out: the run's replay output.
    """

    label: str
    started: str
    files: int
    robots: int
    poses: int
    result: str
    out: str


def verdict_line(verdicts: Sequence[RunVerdict], unreadable_files: int, recording: int = 0) -> str:
    """The last line of an audit over several runs (or files); ``recording``: unfinished logs
    of the folders given that are being recorded now (not audited, not a fault)."""
    kinds = ("passed", "FAILED", UNREADABLE, INCOMPLETE)
    counts = {r: sum(v.result == r for v in verdicts) for r in kinds}
    empty = len(verdicts) - sum(counts.values())
    later = f"; {recording} log(s) being recorded, not audited" if recording else ""
    if counts["FAILED"]:
        return (
            f"audit: [bold red]FAILED[/bold red] ({counts['FAILED']} of {len(verdicts)} runs)"
            + later
        )
    if counts[UNREADABLE] or unreadable_files or counts[INCOMPLETE]:
        parts = [f"{counts[INCOMPLETE]} run(s) not read whole"] if counts[INCOMPLETE] else []
        if counts[UNREADABLE] or unreadable_files:
            parts.append(
                f"{counts[UNREADABLE]} run(s) and {unreadable_files} file(s) could not be read"
            )
        return (
            f"audit: [bold red]incomplete[/bold red]: {'; '.join(parts)}; "
            f"{counts['passed']} run(s) passed" + later
        )
    if not counts["passed"]:
        return f"audit: nothing to audit in {len(verdicts)} runs" + later
    also = f"; {empty} with nothing to audit" if empty else ""
    runs = "run" if counts["passed"] == 1 else "runs"
    return f"audit: [green]passed[/green] ({counts['passed']} {runs}{also}{later})"


def run_verdict(run: LogRun, out: Path, robots: int, poses: int, result: str) -> RunVerdict:
    """One run's line in the final summary."""
    tag = run.tags[0]
    started = "-"
    if tag is not None:
        when = datetime.fromtimestamp(tag.started_ns / 1e9, UTC)
        started = when.isoformat(timespec="seconds").removesuffix("+00:00")
    return RunVerdict(run.short_label, started, len(run.files), robots, poses, result, out.name)


def render_verdicts(verdicts: Sequence[RunVerdict], console: Console) -> None:
    """Print one line per run: the summary of an audit over several runs."""
    table = Table(title=f"Audit of {len(verdicts)} runs")
    for name in ("run", "started (UTC)", "id (instance)", "files", "robots", "recorded poses"):
        table.add_column(name, justify="left" if "(" in name else "right")
    table.add_column("result")
    table.add_column("output", overflow="fold")
    for k, v in enumerate(verdicts, 1):
        colour = {"passed": "green", "FAILED": "bold red"}.get(v.result, "yellow")
        table.add_row(
            str(k),
            v.started,
            v.label,
            str(v.files),
            str(v.robots),
            str(v.poses),
            f"[{colour}]{v.result}[/{colour}]",
            v.out,
        )
    console.print(table)


def written_by(files: Sequence[Path]) -> str | None:
    """What wrote a run's log (its first file's MCAP header, e.g. ``rlutf 0.4.0``); ``None``
    when it cannot be read."""
    from service.logs.mcapread import LogError, LogFile

    try:
        with LogFile(files[0]) as lf:
            return lf.library()
    except LogError:  # the replay said so already
        return None


def version_note(files: Sequence[Path]) -> str | None:
    """Why a failed audit may be no tampering: the log was written by another version of rlutf,
    whose localizer computes other poses (every version that changes a pose is a new version);
    ``None`` when the versions are the same or the writer is not rlutf."""
    from service.logs.mcapfile import LIBRARY

    writer = written_by(files)
    if writer is None or writer == LIBRARY or not writer.startswith("rlutf "):
        return None
    version = writer.removeprefix("rlutf ")
    return (
        f"the log was written by {writer} and replayed by {LIBRARY}: another version's localizer "
        f"computes other poses, so they differ without any tampering; audit it with that "
        f"version (pip install 'rlutf=={version}', or its container image)"
    )
