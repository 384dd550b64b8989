"""Reading logs in the WIRE.md layout, with clear errors for files that are not complete.

A file that does not end in the MCAP magic (cut short by a crash, or still being written as
``.part``), or whose chunks fail their CRC or do not decompress, or whose records it reads are
past the bound or unreadable (:mod:`service.logs.mcaprecords`), raises :class:`DamagedLog`,
whose message says to run ``rlutf log recover``. Callers at the command line turn
:class:`LogError` into an exit code; nothing here prints or exits.

Every message is read or counted: those outside the chunks a chunk index lists are read in
order with the others (:func:`~service.logs.mcaporder.unindexed_spans`), and those on channels
without a schema, whose content cannot be told, are counted per topic as they are met
(:meth:`LogFile.read_counts`), for an audit to say it could not read them.
"""

from __future__ import annotations

import heapq
import io
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, NamedTuple

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, ChunkIndex, Message
from mcap.summary import Summary

from service.infile import open_regular
from service.logs.mcapchunks import inflated_size, unpack_chunk
from service.logs.mcapfile import CONFIG_KEY, CONFIG_METADATA, Record, config_from_metadata
from service.logs.mcaporder import (
    MESSAGE_RECORDS,
    Declarations,
    OffIndex,
    Overlap,
    Redeclared,
    Span,
    SpanScan,
    Triple,
    Unordered,
    chunk_span,
    ordered,
    unindexed_spans,
)
from service.logs.mcaprecords import (
    RecordError,
    read_header,
    read_metadata,
    read_records,
    read_summary,
)
from service.logs.partfile import part_message

MAGIC = b"\x89MCAP0\r\n"


class LogError(Exception):
    """A log that cannot be read; the message says which and why."""


class NotALog(LogError):
    """The file is missing or is not an MCAP file at all."""


class UnreadableConfig(LogError):
    """The log's ``rlutf.config`` record is not a JSON object: a replay cannot trust it."""

    def __init__(self, path: Path, detail: str) -> None:
        super().__init__(
            f"{path}: its rlutf.config record (the configuration it was recorded with) is "
            f"unreadable: {detail}. A replay on other settings would not be an audit; give the "
            "configuration with --settings FILE (or --set KEY=VALUE) to replay it anyway"
        )
        self.path = path


class DamagedLog(LogError):
    """An MCAP file cut short or corrupted: ``rlutf log recover`` can salvage it. One that holds
    a second MCAP file (``cat a.mcap b.mcap``) is named so."""

    def __init__(self, path: Path, detail: str) -> None:
        second = _second_file_at(path)
        super().__init__(
            part_message(path)
            if path.name.endswith(".mcap.part")
            else f"{path}: another MCAP file starts at byte {second:,} (read as this one's, its "
            "bytes made no sense): the file holds more than one (files concatenated?); give each "
            "log as its own file"
            if second is not None
            else f"{path}: {detail}. The file is incomplete or damaged (a crash or a copy cut "
            f"short); salvage its complete chunks with: rlutf log recover {path} FIXED.mcap"
        )
        self.path = path


def _second_file_at(path: Path) -> int | None:
    """Where the magic that starts an MCAP file is found again past the file's start (a second
    of several MCAP files put together), or ``None`` (a search at disk speed, on the error's path
    only)."""
    import mmap

    try:
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            at = m.find(MAGIC + b"\x01", 1)  # a Header record follows a file's first magic
    except (OSError, ValueError):  # not a regular file, or empty
        return None
    return at if at > 0 else None


class UnorderedLog(LogError):
    """A log whose messages are too far out of log-time order to be put in order in bounded
    memory (:mod:`service.logs.mcaporder`): sorted first, it is read."""

    def __init__(self, path: Path, detail: str) -> None:
        super().__init__(
            f"{path}: {detail}. Sort it first, with the mcap CLI: mcap sort {path} -o SORTED.mcap "
            f"(for a file without a chunk index, first: mcap recover {path} -o FIXED.mcap)"
        )
        self.path = path


class RedeclaredLog(LogError):
    """A log that declares a channel (or schema) id twice, differently: its messages on that id
    cannot be told apart, so it is not read."""

    def __init__(self, path: Path, detail: str) -> None:
        super().__init__(
            f"{path}: {detail}: which of its messages are on which cannot be told, so the file "
            "is not read (MCAP allows one definition per id)"
        )
        self.path = path


class ChannelInfo(NamedTuple):
    """One channel of a log and its message count."""

    topic: str
    schema_name: str
    message_encoding: str
    messages: int


class RobotTopic(NamedTuple):
    """A topic ``{prefix}/robots/{robot}/{leaf}`` split up."""

    prefix: str
    robot: str
    leaf: str


def robot_topic(topic: str) -> RobotTopic | None:
    """Split ``{prefix}/robots/{robot}/{leaf}``; ``None`` for other topics."""
    parts = topic.split("/")
    if len(parts) < 4 or parts[-3] != "robots" or not parts[-2] or not parts[-1]:
        return None
    return RobotTopic("/".join(parts[:-3]), parts[-2], parts[-1])


def map_topic(topic: str) -> tuple[str, str] | None:
    """Split ``{prefix}/maps/{map_id}`` into ``(prefix, map_id)``; ``None`` for other topics."""
    parts = topic.split("/")
    if len(parts) < 3 or parts[-2] != "maps" or not parts[-1]:
        return None
    return "/".join(parts[:-2]), parts[-1]


def _lists_every_channel(summary: Summary) -> bool:
    """Whether a summary lists every channel its statistics and chunk indexes name (and some
    channel if it counts messages), and the schema of every channel it lists: a writer may
    leave them out of it (``repeat_channels``, ``repeat_schemas``), and a channel whose schema
    it leaves out would be taken for one without a schema."""
    listed = set(summary.channels)
    stats = summary.statistics
    named = set(stats.channel_message_counts) if stats is not None else set()
    for chunk in summary.chunk_indexes:
        named.update(chunk.message_index_offsets)
    if stats is not None and stats.message_count > 0 and not listed:
        return False
    schemas = {c.schema_id for c in summary.channels.values()} - {0}
    return named <= listed and schemas <= set(summary.schemas)


def _unreadable(what: str, err: Exception) -> str:
    """What went wrong reading a part of a file: a record's own words, or the library's error."""
    if isinstance(err, RecordError):
        return str(err)
    return f"unreadable {what} ({type(err).__name__}: {err})"


def _declared_chunk(index: ChunkIndex) -> Chunk:
    """A chunk with no data that declares the size its index says."""
    return Chunk(
        compression="",
        data=b"",
        message_end_time=0,
        message_start_time=0,
        uncompressed_crc=0,
        uncompressed_size=index.uncompressed_size,
    )


@dataclass(frozen=True)
class _Index:
    channels: dict[int, tuple[str, str, str]]  # id -> topic, schema name, encoding
    counts: dict[int, int]
    start_ns: int | None
    end_ns: int | None


class LogFile:
    """An open, complete log file.

    Args:
        path: the ``.mcap`` file.

    Raises:
        NotALog: missing, unreadable, or not MCAP.
        DamagedLog: truncated or with an unreadable summary.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._scanned: tuple[list[Span], Declarations] | None = None  # see _scan_index
        self._summary: Summary | None = None  # read once, by _check
        self._unindexed: list[Span] | None = None  # messages outside the indexed chunks
        self._read: dict[tuple[str, str], int] = {}  # see read_counts
        self._read_schemas: set[str] | None = set()  # None: all
        try:
            self._stream: IO[bytes] = open_regular(self.path)  # closed in close()
        except OSError as err:
            raise NotALog(f"{self.path}: cannot open: {err.strerror or err}") from err
        try:
            self._index = self._check()
        except BaseException:
            self._stream.close()
            raise

    def _check(self) -> _Index:
        head = self._stream.read(len(MAGIC))
        if head != MAGIC:
            sqlite = head == b"SQLite f"  # "SQLite format 3": a rosbag2 of the sqlite3 storage
            said = ": a rosbag2 recording (sqlite3), which --ros2 reads" if sqlite else ""
            raise NotALog(
                f"{self.path}: not an MCAP file (it does not start with the MCAP magic){said}"
            )
        self._stream.seek(-len(MAGIC), io.SEEK_END)
        if self._stream.tell() < len(MAGIC) or self._stream.read(len(MAGIC)) != MAGIC:
            raise DamagedLog(self.path, "the file does not end with the MCAP magic")
        try:
            summary = self._summary = read_summary(self._stream)
        except Exception as err:  # the library raises many types on garbage
            raise DamagedLog(self.path, _unreadable("summary", err)) from err
        if summary is None:
            return self._scan_index(None)
        names = {i: s.name for i, s in summary.schemas.items()}
        channels = {
            i: (c.topic, names.get(c.schema_id, ""), c.message_encoding)
            for i, c in summary.channels.items()
        }
        stats = summary.statistics
        if stats is None or not _lists_every_channel(summary):
            return self._scan_index(summary)
        counts = dict(stats.channel_message_counts)
        empty = stats.message_count == 0
        return _Index(
            channels,
            counts,
            None if empty else stats.message_start_time,
            None if empty else stats.message_end_time,
        )

    def _scan_index(self, summary: Summary | None) -> _Index:
        """Index a file whose summary lacks statistics, channels or chunk indexes, by reading it
        through once in file order (a chunk at a time): its messages' counts and times, the
        spans to read them by in log-time order (:class:`~service.logs.mcaporder.SpanScan`), and
        the channels and schemas its summary does not list (the MCAP spec leaves repeating them
        there to the writer), which are added to it so that the indexed reads find them.

        Raises:
            RedeclaredLog: a channel or schema id declared twice, differently.
            DamagedLog: a record or chunk cannot be read.
        """
        declared = Declarations(*((summary.schemas, summary.channels) if summary else ()))
        found: set[int] = set()  # the channels the file's records declare
        counts: dict[int, int] = {}
        spans = SpanScan()
        start = end = None
        try:
            with open_regular(self.path) as stream:
                records = read_records(stream, MESSAGE_RECORDS, magic=True, data_crc=True)
                for at, record in records:
                    inner = unpack_chunk(record) if isinstance(record, Chunk) else [record]
                    messages = [m for m in inner if isinstance(m, Message)]
                    for item in inner:
                        if not isinstance(item, Message):
                            declared.add(item)
                            if isinstance(item, Channel):
                                found.add(item.id)
                            continue
                        if item.channel_id not in found:
                            raise McapError(
                                f"a message on channel {item.channel_id}, which no Channel "
                                "record before it declares"
                            )
                        counts[item.channel_id] = counts.get(item.channel_id, 0) + 1
                        t = item.log_time
                        start = t if start is None else min(start, t)
                        end = t if end is None else max(end, t)
                    spans.add(at, stream.tell(), messages)
        except Redeclared as err:
            raise RedeclaredLog(self.path, str(err)) from err
        except Exception as err:  # CRC mismatch, zstd error, short read ...
            raise DamagedLog(self.path, _unreadable("chunk", err)) from err
        self._scanned = spans.spans(), declared
        if summary is not None:
            for i, schema in declared.schemas.items():
                summary.schemas.setdefault(i, schema)
            for i, channel in declared.channels.items():
                summary.channels.setdefault(i, channel)
        names = {i: schema.name for i, schema in declared.schemas.items()}
        channels = {i: declared.channels[i] for i in sorted(found)}
        index = {
            i: (c.topic, names.get(c.schema_id, ""), c.message_encoding)
            for i, c in channels.items()
        }
        return _Index(index, counts, start, end)

    def _iter(self, topics: list[str] | None) -> Iterator[Triple]:
        """Messages (on ``topics``, or all) in log-time order, read a bounded part at a time
        (:func:`~service.logs.mcaporder.ordered`): by the chunk index if the file has one, else
        by the spans a first reading found."""
        try:
            summary = self._summary
            if summary is not None and summary.chunk_indexes:
                for index in summary.chunk_indexes:
                    inflated_size(_declared_chunk(index))  # refused before any is read
                spans = [chunk_span(index) for index in summary.chunk_indexes]
                declared = Declarations(summary.schemas, summary.channels)
                if self._unindexed is None:
                    with open_regular(self.path) as stream:
                        self._unindexed = unindexed_spans(stream, spans, declared, len(MAGIC))
                spans += self._unindexed
            else:
                if self._scanned is None:
                    self._scan_index(summary)
                assert self._scanned is not None
                spans, scanned = self._scanned
                declared = Declarations(scanned.schemas, scanned.channels)
            with open_regular(self.path) as stream:
                yield from ordered(stream, spans, declared, None if topics is None else set(topics))
        except LogError:
            raise
        except Unordered as err:
            raise UnorderedLog(self.path, str(err)) from err
        except Redeclared as err:
            raise RedeclaredLog(self.path, str(err)) from err
        except (OffIndex, Overlap) as err:
            raise DamagedLog(self.path, str(err)) from err
        except Exception as err:  # CRC mismatch, zstd error, short read ...
            raise DamagedLog(self.path, _unreadable("chunk", err)) from err

    # ------------------------------------------------------------------ queries
    def library(self) -> str | None:
        """What wrote the file: its MCAP header's library (``rlutf 0.5.3``, say, for this service's
        logs: the version whose localizer computed its poses); ``None`` if unreadable."""
        try:
            return str(read_header(self._stream).library)
        except Exception:  # the library raises many types on garbage
            return None

    def channels(self) -> list[ChannelInfo]:
        """Every channel, by topic."""
        out = [
            ChannelInfo(topic, schema, encoding, self._index.counts.get(i, 0))
            for i, (topic, schema, encoding) in self._index.channels.items()
        ]
        return sorted(out)

    @property
    def time_range(self) -> tuple[int, int] | None:
        """First and last ``log_time``, ns; ``None`` for a log with no messages."""
        i = self._index
        if i.start_ns is None or i.end_ns is None:
            return None
        return i.start_ns, i.end_ns

    def count(self, schema_names: Collection[str] | None = None) -> int:
        """Messages on channels of these schemas (all if ``None``)."""
        return sum(
            c.messages
            for c in self.channels()
            if schema_names is None or c.schema_name in schema_names
        )

    def metadata(self) -> list[tuple[str, dict[str, str]]]:
        """Every metadata record, in file order."""
        try:
            return [(m.name, dict(m.metadata)) for m in read_metadata(self._stream, self._summary)]
        except Exception as err:
            raise DamagedLog(self.path, _unreadable("metadata", err)) from err

    def schemas(self) -> dict[str, bytes]:
        """Each schema's data by name (empty for a file without a summary)."""
        if self._summary is None:
            return {}
        return {s.name: s.data for s in self._summary.schemas.values()}

    def config(self) -> dict[str, Any] | None:
        """The last ``rlutf.config`` stored, if any.

        Raises:
            UnreadableConfig: a ``rlutf.config`` record is there but is not a JSON object.
        """
        found = None
        for name, data in self.metadata():
            if name == CONFIG_METADATA:
                config = config_from_metadata(data)
                if config is None:
                    text = str(data.get(CONFIG_KEY, ""))
                    raise UnreadableConfig(
                        self.path,
                        f"{CONFIG_KEY!r} is not a JSON object"
                        + (f" (it begins {text[:40]!r})" if text else " (it is missing)"),
                    )
                found = config
        return found

    def messages(self, schema_names: Collection[str] | None = None) -> Iterator[Record]:
        """Messages in ``log_time`` order (file order among equal times).

        Messages on channels without a schema are read too, and counted, not given (unless
        ``schema_names`` is ``None``): what they hold cannot be told (:meth:`read_counts`).

        Args:
            schema_names: only channels with these schema names (all if ``None``).

        Raises:
            DamagedLog: a chunk fails its CRC or does not decompress.
            UnorderedLog: its messages are too far out of order to be put in order in bounded
                memory (refused before the first one).
            RedeclaredLog: a channel or schema id is declared twice, differently.
        """
        read: dict[tuple[str, str], int] = {}
        topics = None
        if schema_names is not None:
            wanted = {*schema_names, ""}
            topics = sorted({c.topic for c in self.channels() if c.schema_name in wanted})
        if topics != []:
            for schema, channel, message in self._iter(topics):
                name = schema.name if schema is not None else ""
                key = (channel.topic, name)
                if schema_names is not None and name not in schema_names:
                    if not name:
                        read[key] = read.get(key, 0) + 1
                    continue
                read[key] = read.get(key, 0) + 1
                yield Record(
                    channel.topic, name, message.data, message.log_time, message.publish_time
                )
        covered = None if schema_names is None else {*schema_names, ""}
        self._tally(covered, read)

    def _tally(self, covered: set[str] | None, read: dict[tuple[str, str], int]) -> None:
        """Keep what a reading through of the schemas ``covered`` (all: ``None``) read."""
        if covered is None:
            self._read, self._read_schemas = dict(read), None
            return
        kept = {k: n for k, n in self._read.items() if k[1] not in covered}
        self._read = kept | read
        if self._read_schemas is not None:
            self._read_schemas |= covered

    def read_counts(self) -> tuple[dict[tuple[str, str], int], set[str] | None]:
        """The messages read per topic and schema name (``""``: a channel without a schema) by
        the last reading through of :meth:`messages` for each schema, and the schema names
        those cover (``None``: every one). Empty until one has been read through."""
        return dict(self._read), None if self._read_schemas is None else set(self._read_schemas)

    def close(self) -> None:
        """Close the file."""
        self._stream.close()

    def __enter__(self) -> LogFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def merged_messages(
    logs: Iterable[LogFile], schema_names: Collection[str] | None = None
) -> Iterator[Record]:
    """Messages of several logs in one ``log_time`` order (earlier files first among ties)."""
    return heapq.merge(*(log.messages(schema_names) for log in logs), key=lambda r: r.log_time_ns)
