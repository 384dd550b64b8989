"""``rlutf log`` tools: what a log holds (:func:`log_info`) and repairing a cut-short file
(:func:`recover`).

Recovery reads the damaged file front to back with :class:`mcap.stream_reader.StreamReader` and
copies every record of every complete chunk (schemas, channels, messages) and every metadata and
attachment record into a new, complete file. A chunk that fails its CRC or does not decompress
is skipped and counted; reading stops at the first record that is cut short or unreadable.
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from mcap.records import Attachment, Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer
from rich.console import Console
from rich.table import Table

from service.logs.mcapread import MAGIC, ChannelInfo, LogFile, NotALog, map_topic, robot_topic


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

    @property
    def messages(self) -> int:
        """Messages in the log."""
        return sum(c.messages for c in self.channels)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready data (``rlutf log info --json``)."""
        data = asdict(self)
        data["channels"] = [c._asdict() for c in self.channels]
        data["messages"] = self.messages
        return data


def log_info(path: Path) -> LogInfo:
    """Channels, counts, time range, robots, maps and configuration of a log.

    Every chunk is read (and its CRC checked), so a damaged file is reported.

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
        maps: dict[str, list[int]] = defaultdict(list)
        for rec in lf.messages():  # all of them: a damaged chunk is found, not ignored
            if rec.schema_name != "rlutf.Map":
                continue
            where_map = map_topic(rec.topic)
            try:
                version = json.loads(rec.payload).get("version")
            except (ValueError, AttributeError):
                version = None
            if where_map is not None and isinstance(version, int):
                maps[where_map[1]].append(version)
        return LogInfo(
            str(path),
            path.stat().st_size,
            channels,
            lf.time_range,
            dict(sorted(robots.items())),
            {k: sorted(set(v)) for k, v in maps.items()},
            lf.config(),
            [name for name, _ in lf.metadata()],
        )


def _when(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")


def render_info(info: LogInfo, console: Console) -> None:
    """Print a log's info as tables."""
    console.print(f"[bold]{info.path}[/bold]  {info.size:,} bytes, {info.messages:,} messages")
    if info.time_range is not None:
        start, end = info.time_range
        console.print(f"time: {_when(start)} .. {_when(end)}  ({(end - start) / 1e9:.3f} s)")
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
    if info.robots:
        leaves = sorted({leaf for counts in info.robots.values() for leaf in counts})
        robots = Table(title="robots")
        robots.add_column("robot")
        for leaf in leaves:
            robots.add_column(leaf, justify="right")
        for robot, counts in info.robots.items():
            robots.add_row(robot, *(f"{counts.get(leaf, 0):,}" for leaf in leaves))
        console.print(robots)
    for map_id, versions in sorted(info.maps.items()):
        console.print(f"map {map_id}: version(s) {', '.join(map(str, versions))}")


@dataclass
class RecoverReport:
    """What :func:`recover` salvaged.

    Attributes:
        messages: messages copied.
        chunks: complete chunks copied.
        bad_chunks: chunks skipped (CRC mismatch or not decompressible).
        lost_messages: messages skipped because their channel record was lost.
        metadata: metadata records copied.
        complete: the input's footer was reached (nothing was missing).
        stopped: why reading stopped before the footer, if it did.
        stopped_at: byte offset where it stopped.
    """

    messages: int = 0
    chunks: int = 0
    bad_chunks: int = 0
    lost_messages: int = 0
    metadata: int = 0
    complete: bool = False
    stopped: str | None = None
    stopped_at: int | None = None
    channels: dict[int, int] = field(default_factory=dict, repr=False)
    schemas: dict[int, int] = field(default_factory=dict, repr=False)


class _Copier:
    def __init__(self, writer: Writer, report: RecoverReport) -> None:
        self.writer = writer
        self.report = report
        self.started = False

    def start(self, header: Header | None) -> None:
        if not self.started:
            self.started = True
            self.writer.start(
                profile=header.profile if header else "",
                library=header.library if header else "rlutf recover",
            )

    def take(self, rec: Any) -> None:
        r, w = self.report, self.writer
        if isinstance(rec, Schema) and rec.id not in r.schemas:
            r.schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel) and rec.id not in r.channels:
            schema = r.schemas.get(rec.schema_id, 0)
            r.channels[rec.id] = w.register_channel(
                rec.topic, rec.message_encoding, schema, dict(rec.metadata)
            )
        elif isinstance(rec, Message):
            channel = r.channels.get(rec.channel_id)
            if channel is None:
                r.lost_messages += 1
                return
            w.add_message(channel, rec.log_time, rec.data, rec.publish_time, rec.sequence)
            r.messages += 1
        elif isinstance(rec, Metadata):
            w.add_metadata(rec.name, dict(rec.metadata))
            r.metadata += 1
        elif isinstance(rec, Attachment):
            w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)


def _copy(src: IO[bytes], writer: Writer, report: RecoverReport) -> None:
    copier = _Copier(writer, report)
    try:
        for rec in StreamReader(src, emit_chunks=True).records:
            if isinstance(rec, Header):
                copier.start(rec)
                continue
            copier.start(None)
            if isinstance(rec, Chunk):
                try:
                    inner = breakup_chunk(rec, validate_crc=True)
                except Exception:  # bad CRC or compression: skip this chunk only
                    report.bad_chunks += 1
                    continue
                for item in inner:
                    copier.take(item)
                report.chunks += 1
            elif isinstance(rec, Footer):
                report.complete = True
            else:
                copier.take(rec)
    except Exception as err:  # the cut: a short read, or garbage where a record should start
        report.stopped = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        report.stopped_at = src.tell()
    copier.start(None)


def recover(src: Path, dst: Path) -> RecoverReport:
    """Copy everything readable of ``src`` into a new complete log ``dst``.

    Raises:
        NotALog: ``src`` is missing or not MCAP, or ``dst`` is ``src``.
    """
    if dst.exists() and dst.resolve() == src.resolve():
        raise NotALog(f"{dst}: the output must not be the input")
    try:
        stream = open(src, "rb")  # noqa: SIM115 -- closed below
    except OSError as err:
        raise NotALog(f"{src}: cannot open: {err.strerror or err}") from err
    with stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise NotALog(f"{src}: not an MCAP file (it does not start with the MCAP magic)")
        stream.seek(0)
        report = RecoverReport()
        part = dst.with_name(dst.name + ".part")
        try:
            with open(part, "wb") as out:
                writer = Writer(out, compression=CompressionType.ZSTD)
                _copy(stream, writer, report)
                writer.finish()
                out.flush()
                os.fsync(out.fileno())
        except BaseException:
            part.unlink(missing_ok=True)
            raise
    os.replace(part, dst)
    return report
