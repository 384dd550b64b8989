"""A log's messages in ``log_time`` order, with a bounded part of the log held at once.

The ``mcap`` library puts a file's messages in order by sorting all of them in memory when the
file has no chunk index (a crashed recording, or another tool's): 23 MB held to read 20 MB of
messages a little out of order, 229 MB for a log ten times as long (1.6 and 1.5 MB here). With a
chunk index it keeps every chunk whose messages overlap the next one's in time: a 0.5 MB file
whose every chunk spans the whole log took 47 MB.

Here a file is read as :class:`Span` s, each a stretch of it (a chunk, or about
:data:`SPAN_BYTES` of consecutive records) with the times of its messages, from the chunk index
or, for a file without one, from reading it through once (:class:`SpanScan`); beside a chunk
index, the messages outside the chunks it lists (written outside chunks, or in chunks it leaves
out, which the library's indexed reader never reads) are found by reading the stretches between
them (:func:`unindexed_spans`). Spans are opened
in the order of their first message's time and their messages given once no span still unopened
can hold an earlier one (:func:`ordered`), in the order the library gives: ``log_time``, then
file order. A log in order, or nearly (a recorder's threads hand it messages a little out of
order), holds a span or two; one whose spans overlap past :data:`MAX_OPEN_BYTES` is refused
(:class:`Unordered`) before its first message, rather than read with no bound.

Schemas and channels are checked as they are declared (:class:`Declarations`): an id declared
twice differently would give messages of one topic to another.
"""

from __future__ import annotations

import heapq
from collections.abc import Collection, Iterable, Iterator, Mapping, Sequence
from typing import IO, Final, NamedTuple

from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, McapRecord, Message, Schema

from service.logs.mcapchunks import MAX_CHUNK_BYTES, unpack_chunk
from service.logs.mcaprecords import read_records

#: Most bytes of messages held at once to put a file's messages in order (a span alone, bounded
#: by :data:`~service.logs.mcapchunks.MAX_CHUNK_BYTES` as a chunk, is always read).
MAX_OPEN_BYTES: Final = MAX_CHUNK_BYTES
#: A span of a file without a chunk index is cut once it holds about this many bytes.
SPAN_BYTES: Final = 1 << 20
#: What holding a message costs besides its payload (its fields, the objects that hold it), bytes:
#: about 340 measured for an empty one. A file of empty messages is bounded too.
MESSAGE_COST: Final = 320

Triple = tuple[Schema | None, Channel, Message]
#: The records whose messages and declarations are read (others are skipped, not read).
MESSAGE_RECORDS: Final = frozenset({Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.CHUNK})


class Span(NamedTuple):
    """A stretch of an MCAP file whose messages are read together.

    Attributes:
        offset: where its first record starts in the file, bytes.
        end: where its last record ends, bytes.
        start_ns: the earliest ``log_time`` of its messages.
        end_ns: the latest.
        size: what its messages cost held (:data:`MESSAGE_COST` each besides the payload), or a
            chunk index's decompressed size, bytes.
        channels: the channel ids of its messages, if known (a chunk index may list them).
    """

    offset: int
    end: int
    start_ns: int
    end_ns: int
    size: int
    channels: frozenset[int] | None = None


def chunk_span(index: ChunkIndex) -> Span:
    """A chunk's span, as its index describes it."""
    return Span(
        index.chunk_start_offset,
        index.chunk_start_offset + index.chunk_length,
        index.message_start_time,
        index.message_end_time,
        index.uncompressed_size,
        frozenset(index.message_index_offsets) or None,
    )


def _cost(message: Message) -> int:
    return len(message.data) + MESSAGE_COST


class Unordered(ValueError):
    """Spans that overlap in time past the bound: the messages are too far out of order."""

    def __init__(self, at_ns: int, held: int, limit: int) -> None:
        super().__init__(
            f"its messages are too far out of log-time order to be put in order a part at a time: "
            f"at log time {at_ns} ns, {held:,} bytes of them overlap in time, past the {limit:,} "
            "bytes rlutf holds at once (a log the service writes overlaps by a chunk or two)"
        )
        self.at_ns, self.held, self.limit = at_ns, held, limit


class OffIndex(ValueError):
    """A message outside the times its chunk's index declares: the index cannot be trusted."""

    def __init__(self, span: Span, log_time: int) -> None:
        super().__init__(
            f"the chunk at byte {span.offset} holds a message at log time {log_time} ns, outside "
            f"the times its index declares ({span.start_ns} to {span.end_ns} ns)"
        )


class Redeclared(ValueError):
    """A schema or channel id declared twice, differently."""


def _about_channel(channel: Channel, schemas: Mapping[int, Schema]) -> str:
    schema = schemas.get(channel.schema_id)
    name = schema.name if schema is not None else f"schema id {channel.schema_id}"
    return f"topic {channel.topic!r} ({name}, {channel.message_encoding})"


class Declarations:
    """A file's schemas and channels by id, each declared once, or again the same.

    The MCAP format allows one definition per id; a second one that differs in what a reader goes
    by (a channel's topic, schema or encoding; a schema's name or encoding) is refused, as which
    of the messages on that id belong to which cannot be told. Declarations from ``schemas`` and
    ``channels`` (a summary's) are checked against as well.
    """

    def __init__(
        self,
        schemas: Mapping[int, Schema] | None = None,
        channels: Mapping[int, Channel] | None = None,
    ) -> None:
        self.schemas: dict[int, Schema] = dict(schemas or {})
        self.channels: dict[int, Channel] = dict(channels or {})

    def add(self, record: McapRecord) -> None:
        """Take a Schema or Channel record (other records are left alone).

        Raises:
            Redeclared: its id was declared before as something else.
        """
        if isinstance(record, Schema):
            known = self.schemas.setdefault(record.id, record)
            if (known.name, known.encoding) != (record.name, record.encoding):
                raise Redeclared(
                    f"schema {record.id} is declared twice, as {known.name!r} ({known.encoding}) "
                    f"and as {record.name!r} ({record.encoding})"
                )
        elif isinstance(record, Channel):
            was = self.channels.setdefault(record.id, record)
            fields = (was.topic, was.schema_id, was.message_encoding)
            if fields != (record.topic, record.schema_id, record.message_encoding):
                raise Redeclared(
                    f"channel {record.id} is declared twice, as "
                    f"{_about_channel(was, self.schemas)} and as "
                    f"{_about_channel(record, self.schemas)}"
                )

    def triple(self, message: Message) -> Triple:
        """A message with its schema and channel.

        Raises:
            ValueError: its channel, or the channel's schema, is not declared.
        """
        channel = self.channels.get(message.channel_id)
        if channel is None:
            raise ValueError(
                f"a message on channel {message.channel_id}, which no Channel record declares"
            )
        if channel.schema_id == 0:
            return None, channel, message
        schema = self.schemas.get(channel.schema_id)
        if schema is None:
            raise ValueError(
                f"channel {channel.id} ({channel.topic!r}) names schema {channel.schema_id}, "
                "which no Schema record declares"
            )
        return schema, channel, message


class SpanScan:
    """The spans of a file read through in file order: records are handed in as they are read,
    with where they lie, and cut into spans of about :data:`SPAN_BYTES` (:meth:`spans`).

    Records without messages between two that have some are read again with their span, as long
    as they are short; a long one (an attachment) ends the span before it.
    """

    def __init__(self) -> None:
        self._done: list[Span] = []
        self._open: Span | None = None

    def add(self, offset: int, end: int, messages: Sequence[Message]) -> None:
        """Take the record at ``[offset, end)`` of the file and the messages it holds (a chunk's,
        or one message's)."""
        times = [m.log_time for m in messages]
        if not times:
            return
        size = sum(_cost(m) for m in messages)
        span, self._open = self._open, None
        if span is not None and offset - span.end > SPAN_BYTES:
            self._done.append(span)
            span = None
        if span is None:
            span = Span(offset, end, min(times), max(times), size)
        else:
            span = Span(
                span.offset,
                end,
                min(span.start_ns, *times),
                max(span.end_ns, *times),
                span.size + size,
            )
        if span.size >= SPAN_BYTES or span.end - span.offset >= SPAN_BYTES:
            self._done.append(span)
        else:
            self._open = span

    def cut(self) -> None:
        """End the open span: the next record starts another."""
        if self._open is not None:
            self._done.append(self._open)
            self._open = None

    def spans(self) -> list[Span]:
        """Every span, in file order."""
        self.cut()
        return self._done


class Overlap(ValueError):
    """A record outside the indexed chunks that runs into one: the chunk index cannot be
    trusted."""


def unindexed_spans(
    stream: IO[bytes], indexed: Sequence[Span], declared: Declarations, start: int
) -> list[Span]:
    """The spans of a file's messages outside the chunks its chunk index lists: messages written
    outside chunks (MCAP allows them beside indexed chunks, and the ``mcap`` library's indexed
    reader never reads them) and chunks the index leaves out. Found by reading the stretches of
    the data section between the indexed chunks (from ``start``, after the header, to the data
    end record) a record at a time, each bounded as :func:`span_records` bounds it; the others
    there (message indexes, metadata, attachments) are skipped unread. Schemas and channels
    declared there are added to ``declared``.

    Raises:
        Overlap: a record there runs into an indexed chunk.
        Redeclared: a schema or channel declared again differently.
        Exception: as :func:`span_records`.
    """
    scan = SpanScan()
    wanted = MESSAGE_RECORDS | {Opcode.DATA_END}
    chunks = sorted(indexed, key=lambda s: s.offset)
    at = start
    for k in range(len(chunks) + 1):
        until = chunks[k].offset if k < len(chunks) else None
        if until is None or until > at:
            stream.seek(at)
            for offset, record in read_records(stream, wanted, end=until):
                if isinstance(record, DataEnd):
                    return scan.spans()
                if until is not None and stream.tell() > until:
                    raise Overlap(
                        f"the record at byte {offset} runs into the chunk at byte {until} that "
                        "the chunk index lists"
                    )
                inner = unpack_chunk(record) if isinstance(record, Chunk) else [record]
                for item in inner:
                    if not isinstance(item, Message):
                        declared.add(item)
                scan.add(offset, stream.tell(), [m for m in inner if isinstance(m, Message)])
        scan.cut()  # a span never spans an indexed chunk: it would be read twice
        if until is not None:
            at = max(at, chunks[k].end)
    return scan.spans()


def check_overlap(spans: Iterable[Span], limit: int | None = None) -> None:
    """Refuse spans that would be held past ``limit`` at once (by default
    :data:`MAX_OPEN_BYTES`), going by their declared times and sizes: before reading, so that a
    log too far out of order fails at once, not after a replay of hours.

    Raises:
        Unordered: at the start of some span, it and the spans opened before it that end at or
            after that time hold more than ``limit`` bytes.
    """
    limit = MAX_OPEN_BYTES if limit is None else limit
    opened: list[tuple[int, int]] = []  # (end_ns, size) of the spans that may hold messages
    held = 0
    for span in sorted(spans, key=lambda s: (s.start_ns, s.offset)):
        while opened and opened[0][0] < span.start_ns:
            held -= heapq.heappop(opened)[1]
        if held and held + span.size > limit:
            raise Unordered(span.start_ns, held + span.size, limit)
        heapq.heappush(opened, (span.end_ns, span.size))
        held += span.size


def span_records(stream: IO[bytes], span: Span) -> Iterator[McapRecord]:
    """The schemas, channels and messages of a span, a chunk's own records in its place (each
    record bounded by :func:`~service.logs.mcaprecords.read_records`, each chunk by
    :func:`~service.logs.mcapchunks.unpack_chunk`)."""
    stream.seek(span.offset)
    for _, record in read_records(stream, MESSAGE_RECORDS, end=span.end):
        if isinstance(record, Chunk):
            yield from unpack_chunk(record)
        else:
            yield record


def ordered(
    stream: IO[bytes],
    spans: Iterable[Span],
    declared: Declarations,
    topics: Collection[str] | None = None,
    limit: int | None = None,
) -> Iterator[Triple]:
    """The messages of ``spans`` (on ``topics``, or all) in ``log_time`` order, file order among
    equal times, each with its schema and channel.

    Raises:
        Unordered: the spans overlap past ``limit`` (by default :data:`MAX_OPEN_BYTES`).
        OffIndex: a message outside its span's times: a chunk index that lies.
        Redeclared: a schema or channel declared again differently.
        ValueError: a message on an undeclared channel, or a chunk past the bound.
        Exception: whatever the ``mcap`` library raises on a damaged record.
    """
    limit = MAX_OPEN_BYTES if limit is None else limit

    def wanted(span: Span) -> bool:
        if topics is None or span.channels is None:
            return True
        known = (declared.channels.get(i) for i in span.channels)
        return any(c is None or c.topic in topics for c in known)

    chosen = [s for s in spans if wanted(s)]
    check_overlap(chosen, limit)
    heap: list[tuple[int, int, int, Triple]] = []
    held = 0
    for span in sorted(chosen, key=lambda s: (s.start_ns, s.offset)):
        while heap and heap[0][:2] < (span.start_ns, span.offset):
            item = heapq.heappop(heap)[3]
            held -= _cost(item[2])
            yield item
        before = held
        for i, record in enumerate(span_records(stream, span)):
            if not isinstance(record, Message):
                declared.add(record)
                continue
            if not span.start_ns <= record.log_time <= span.end_ns:
                raise OffIndex(span, record.log_time)
            triple = declared.triple(record)
            if topics is not None and triple[1].topic not in topics:
                continue
            heapq.heappush(heap, (record.log_time, span.offset, i, triple))
            held += _cost(record)
        if before and held > limit:
            raise Unordered(span.start_ns, held, limit)
    while heap:
        yield heapq.heappop(heap)[3]
