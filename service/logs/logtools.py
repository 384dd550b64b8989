"""``rlutf log info``: what a log holds (:func:`log_info`), one file or several by run
(:func:`runs_info`). Repairing a cut-short file, ``rlutf log recover``, is
:func:`service.logs.salvage.recover`.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from service.logs.completeness import Completeness, FileCheck, check_file, completeness
from service.logs.mcapread import (
    ChannelInfo,
    LogError,
    LogFile,
    UnreadableConfig,
    map_topic,
    robot_topic,
)
from service.logs.runs import LogRun, RunTag, foreign, group_runs, run_tag


@dataclass
class LogInfo:
    """What :func:`log_info` found in a log."""

    path: str
    size: int
    channels: list[ChannelInfo]
    time_range: tuple[int, int] | None
    robots: dict[str, dict[str, int]]
    maps: dict[str, list[int]]
    config: dict[str, Any] | None
    metadata: list[str]
    run: dict[str, str] | None = None
    carried_maps: int = 0
    writer: str | None = None
    foreign: str | None = None
    """Why the file is no rlutf log (:func:`service.logs.runs.foreign`: a rosbag2 recording,
    another tool's MCAP), with the command that reads it; ``None`` for an rlutf log."""
    check: FileCheck | None = field(default=None, repr=False)
    """What it holds that could not be read, and how it compares with its ``rlutf.manifest``
    (:mod:`service.logs.completeness`)."""

    @property
    def messages(self) -> int:
        """Messages in the log."""
        return sum(c.messages for c in self.channels)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready data (``rlutf log info --json``): with ``unread`` (messages per topic on
        channels without a schema), ``recovered`` (its ``rlutf.recovered`` records) and
        ``manifest`` (``null`` without one, else ``{"last", "differs": [[topic, schema, listed,
        read], ...]}``)."""
        check = self.check
        data = asdict(replace(self, check=None))
        del data["check"]
        data["channels"] = [c._asdict() for c in self.channels]
        data["messages"] = self.messages
        data["unread"] = dict(check.unread) if check is not None else {}
        data["recovered"] = [r.to_metadata() for r in check.recovered] if check else []
        manifest = check.manifest if check is not None else None
        data["manifest"] = None
        if check is not None and manifest is not None:
            data["manifest"] = {"last": manifest.last, "differs": [list(d) for d in check.differs]}
        return data


def log_info(path: Path) -> LogInfo:
    """Channels, counts, time range, robots, maps and configuration of a log.

    Every chunk is read (and its CRC checked), so a damaged file is reported, and so are the
    messages it holds that cannot be read (on channels without a schema) and how it compares
    with its ``rlutf.manifest`` (``check``). ``run`` is the
    file's ``rlutf.run`` metadata. A file the recorder opened after rotating starts with the
    maps recorded before it, at their original ``log_time``: those are counted in
    ``carried_maps`` and left out of ``time_range``, which spans the file's own messages.

    Raises:
        service.logs.mcapread.LogError: the file is missing, not MCAP, or damaged.
    """
    with LogFile(path) as lf:
        channels = lf.channels()
        robots: dict[str, dict[str, int]] = defaultdict(dict)
        for c in channels:
            where = robot_topic(c.topic) if c.schema_name.startswith("rlutf.") else None
            if where is not None:
                counts = robots[where.robot]
                counts[where.leaf] = counts.get(where.leaf, 0) + c.messages
        tag = run_tag(lf)
        opened = tag.opened_ns if tag is not None else None
        maps: dict[str, list[int]] = defaultdict(list)
        carried = 0
        first = last = None
        for rec in lf.messages():  # all of them: a damaged chunk is found, not ignored
            if (
                opened is not None
                and rec.log_time_ns < opened
                and _is_map(rec.topic, rec.schema_name)
            ):
                carried += rec.schema_name == "rlutf.Map"
            else:
                t = rec.log_time_ns
                first = t if first is None or t < first else first
                last = t if last is None or t > last else last
            if rec.schema_name != "rlutf.Map":
                continue
            where_map = map_topic(rec.topic)
            try:
                version = json.loads(rec.payload).get("version")
            except (ValueError, AttributeError, RecursionError):
                version = None
            if where_map is not None and isinstance(version, int):
                maps[where_map[1]].append(version)
        return LogInfo(
            str(path),
            path.stat().st_size,
            channels,
            None if first is None or last is None else (first, last),
            dict(sorted(robots.items())),
            {k: sorted(set(v)) for k, v in maps.items()},
            _config_or_none(lf),
            [name for name, _ in lf.metadata()],
            tag.to_metadata() if tag is not None else None,
            carried,
            lf.library(),
            foreign(lf),
            check_file(lf, tag),
        )


def _config_or_none(lf: LogFile) -> dict[str, Any] | None:
    try:
        return lf.config()
    except UnreadableConfig:
        return None


def _is_map(topic: str, schema_name: str) -> bool:
    """A map or its Foxglove view: what a rotated file carries over from earlier files."""
    return schema_name == "rlutf.Map" or topic.startswith("/foxglove/maps/")


def _when(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")


def _clock(ns: int) -> str:
    """Time of day (UTC) to the millisecond; the date is on the run's line."""
    return datetime.fromtimestamp(ns / 1e9, UTC).strftime("%H:%M:%S.%f")[:-3]


def render_info(info: LogInfo, console: Console) -> None:
    """Print a log's info as tables."""
    console.print(f"[bold]{info.path}[/bold]  {info.size:,} bytes, {info.messages:,} messages")
    # The version whose localizer computed the poses: audit the log with that version.
    console.print(f"written by: {info.writer or 'unknown'}")
    run = info.run
    if run is not None:
        raw = run.get("started_ns")
        started = (
            _when(int(raw))
            if raw is not None and raw.isdigit()
            else f"unknown (started_ns {'missing' if raw is None else repr(raw)}: this record "
            "is damaged)"
        )
        console.print(
            f"run: {run.get('run_id')}, instance {run.get('instance') or '?'}, started "
            f"{started}, file number {run.get('sequence', '?')} in the run (from 0)"
        )
    else:
        console.print("run: none recorded (rlutf.run missing: not written by rlutf 0.3 or later)")
    if info.time_range is not None:
        start, end = info.time_range
        console.print(f"time: {_when(start)} .. {_when(end)}  ({(end - start) / 1e9:.3f} s)")
    if info.carried_maps:
        console.print(
            f"starts with {info.carried_maps} map message(s) carried over from the run's "
            "earlier files (at their original log_time, outside the time above)"
        )
    cfg = info.config
    if cfg is not None:
        console.print(
            f"config: instance {cfg.get('instance', '?')}, prefix "
            f"{cfg.get('prefix', '?')}, workers {cfg.get('workers', '?')}"
        )
    else:
        console.print("config: none recorded (replay uses the defaults)")
    table = Table(title="channels")
    for name in ("topic", "schema", "encoding", "messages"):
        table.add_column(name, justify="right" if name == "messages" else "left")
    for c in info.channels:
        table.add_row(c.topic, c.schema_name or "-", c.message_encoding, f"{c.messages:,}")
    console.print(table)
    _render_robots(info.robots, console, "robots")
    for map_id, versions in sorted(info.maps.items()):
        console.print(f"map {map_id}: version(s) {', '.join(map(str, versions))}")
    if info.foreign is not None:
        console.print(f"[yellow]{info.foreign}[/yellow]", soft_wrap=True)
    if info.check is not None:
        tag = RunTag.from_metadata(info.run) if info.run is not None else None
        _render_notes(completeness([info.check], [tag]), console, run=False)


def _render_notes(whole: Completeness, console: Console, run: bool = True) -> None:
    """What the files hold that was not read, or not what their manifests list (and, with
    ``run``, the run's files not given)."""
    for kind, text in whole.notes(run):
        colour = {"altered": "red", "incomplete": "bold yellow"}.get(kind, "yellow")
        console.print(f"[{colour}]{escape(text)}[/{colour}]", soft_wrap=True)


@dataclass
class RunInfo:
    """What :func:`runs_info` found about one run: the run and each of its files."""

    run: LogRun
    files: list[LogInfo]

    @property
    def time_range(self) -> tuple[int, int] | None:
        """First and last ``log_time`` of the run's own messages."""
        spans = [f.time_range for f in self.files if f.time_range is not None]
        if not spans:
            return None
        return min(a for a, _ in spans), max(b for _, b in spans)

    @property
    def robots(self) -> dict[str, dict[str, int]]:
        """Messages per robot and leaf, summed over the files."""
        out: dict[str, dict[str, int]] = defaultdict(dict)
        for f in self.files:
            for robot, counts in f.robots.items():
                for leaf, n in counts.items():
                    out[robot][leaf] = out[robot].get(leaf, 0) + n
        return dict(sorted(out.items()))

    @property
    def completeness(self) -> Completeness:
        """What the run's files hold that was not read, how they compare with their
        manifests, and the run's files not given."""
        checks = [f.check or FileCheck(Path(f.path), None) for f in self.files]
        return completeness(checks, self.run.tags)

    @property
    def maps(self) -> dict[str, list[int]]:
        """Versions per map id over the files."""
        out: dict[str, set[int]] = defaultdict(set)
        for f in self.files:
            for map_id, versions in f.maps.items():
                out[map_id].update(versions)
        return {k: sorted(v) for k, v in sorted(out.items())}

    def to_json(self) -> dict[str, Any]:
        """JSON-ready data (an item of ``runs`` in ``rlutf log info --json``)."""
        first = self.run.tags[0]
        return {
            "run_id": self.run.run_id,
            "instance": self.run.instance,
            "started_ns": first.started_ns if first is not None else None,
            "missing_files": self.run.missing,
            "skipped_files": self.run.skipped,
            "notes": [{"kind": k, "text": t} for k, t in self.completeness.notes()],
            "time_range": self.time_range,
            "messages": sum(f.messages for f in self.files),
            "robots": self.robots,
            "maps": self.maps,
            "files": [f.to_json() for f in self.files],
        }


def runs_info(
    paths: Sequence[Path], unreadable: list[tuple[Path, LogError]] | None = None
) -> list[RunInfo]:
    """:func:`log_info` of every file, grouped by run (:func:`service.logs.runs.group_runs`).

    Args:
        paths: the files.
        unreadable: if given, files that cannot be read are added to it with their error and
            left out (their run reports them missing), instead of raising.

    Raises:
        service.logs.mcapread.LogError: a file is missing, not MCAP, or damaged (unless
            ``unreadable`` is given), or two files claim the same place in a run.
    """
    out = []
    for run in group_runs(paths, unreadable):
        kept: list[tuple[Path, RunTag | None, LogInfo]] = []
        for path, tag in zip(run.files, run.tags, strict=True):
            try:
                kept.append((path, tag, log_info(path)))
            except LogError as err:
                if unreadable is None:
                    raise
                unreadable.append((path, err))
        if kept:
            files = LogRun(tuple(k[0] for k in kept), tuple(k[1] for k in kept), run.start_ns)
            out.append(RunInfo(files, [k[2] for k in kept]))
    return out


def render_runs(runs: Sequence[RunInfo], console: Console) -> None:
    """Print several files' info, run by run: a line per run, a table of its files, its
    robots and maps."""
    for k, info in enumerate(runs, 1):
        run = info.run
        first = run.tags[0]
        started = f", started {_when(first.started_ns)}" if first is not None else ""
        console.rule(f"run {k} of {len(runs)}: {run.label}{started}")
        writers = sorted({f.writer or "unknown" for f in info.files})
        console.print(f"written by: {', '.join(writers)}")
        span = info.time_range
        if span is not None:
            start, end = span
            console.print(f"time: {_when(start)} .. {_when(end)}  ({(end - start) / 1e9:.3f} s)")
        table = Table(title=f"files of run {k}")
        for name in ("file #", "file", "bytes", "messages", "from", "to", "carried maps"):
            table.add_column(name, justify="left" if name == "file" else "right")
        for tag, f in zip(run.tags, info.files, strict=True):
            start_s, end_s = ("-", "-") if f.time_range is None else map(_clock, f.time_range)
            table.add_row(
                str(tag.sequence) if tag is not None else "-",
                Path(f.path).name,
                f"{f.size:,}",
                f"{f.messages:,}",
                start_s,
                end_s,
                str(f.carried_maps),
            )
        console.print(table)
        _render_robots(info.robots, console, f"robots of run {k}")
        for map_id, versions in info.maps.items():
            console.print(f"map {map_id}: version(s) {', '.join(map(str, versions))}")
        _render_notes(info.completeness, console)


def _render_robots(robots: dict[str, dict[str, int]], console: Console, title: str) -> None:
    if not robots:
        return
    leaves = sorted({leaf for counts in robots.values() for leaf in counts})
    table = Table(title=title)
    table.add_column("robot")
    for leaf in leaves:
        table.add_column(leaf, justify="right")
    for robot, counts in robots.items():
        table.add_row(robot, *(f"{counts.get(leaf, 0):,}" for leaf in leaves))
    console.print(table)
