"""MCAP records read within a bound, whatever lengths a file declares.

The ``mcap`` library reads a record whole, to the length its head declares, up to 4 GiB, and
trusts the lengths inside it (a chunk's or an attachment's data, a string, a map) even where they
run past the record's end; a message record one byte short of its fixed fields reads the rest of
the file; a record's padding and a record of an unknown opcode are read into memory too. A
sparse file of a few kilobytes on disk holding one attachment, message, metadata or schema
record of 513 MiB took 0.5 to 1 GiB to read as ``rlutf log info`` and ``rlutf replay`` read it,
up to 1.6 GB with ``rlutf log recover``; a footer whose summary start points at the data section
had the library decompress a chunk whole there (1.1 GB for one of 513 MiB).

Here (:func:`read_records`) a record is read only if it lies within the file and its length is
at most :data:`MAX_RECORD_BYTES` (the chunk bound, with room for a chunk's own fields); it is
parsed by the library's own record classes from a window of exactly that length, where a field
that runs past the end is an error (:class:`RecordOverrun`). Padding, records of unknown
opcodes and those the caller does not use (an attachment, to the readers, which never use one)
are skipped, not read. The summary, header and metadata a reader looks up are read the same way
(:func:`read_summary`, :func:`read_header`, :func:`read_metadata`).
"""

from __future__ import annotations

import io
import os
import zlib
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import IO, Final

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.summary import Summary

from service.infile import open_regular
from service.logs.mcapchunks import MAX_CHUNK_BYTES, ChunkTooLarge, inflated_size

#: Largest record read, bytes: a chunk of :data:`~service.logs.mcapchunks.MAX_CHUNK_BYTES` and its
#: fields. The service's records are a chunk (about a megabyte) or a map (``max_map_bytes``).
MAX_RECORD_BYTES: Final = MAX_CHUNK_BYTES + (64 << 10)
MAGIC: Final = b"\x89MCAP0\r\n"
_HEAD: Final = 9  # opcode, length
_FOOTER: Final = _HEAD + 8 + 8 + 4
_PIECE: Final = 1 << 20
_SMALL: Final = 1 << 16

_RECORDS: Final[dict[int, type[McapRecord]]] = {
    Opcode.ATTACHMENT: Attachment,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK: Chunk,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.DATA_END: DataEnd,
    Opcode.FOOTER: Footer,
    Opcode.HEADER: Header,
    Opcode.MESSAGE: Message,
    Opcode.MESSAGE_INDEX: MessageIndex,
    Opcode.METADATA: Metadata,
    Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.SCHEMA: Schema,
    Opcode.STATISTICS: Statistics,
    Opcode.SUMMARY_OFFSET: SummaryOffset,
}
#: What a summary holds that a reader uses.
SUMMARY_RECORDS: Final = frozenset(
    {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.STATISTICS, Opcode.CHUNK_INDEX, Opcode.METADATA_INDEX}
)


_ROSBAGS_READS: Final = frozenset(_RECORDS) - {Opcode.ATTACHMENT, Opcode.METADATA}


def _kind(opcode: int) -> str:
    known = _RECORDS.get(opcode)
    return known.__name__ if known is not None else f"opcode 0x{opcode:02x}"


class RecordError(ValueError):
    """A record that is not read: past the bound, past the end of the file, or not a record."""


class RecordTooLarge(RecordError):
    """A record longer than the bound."""

    def __init__(self, opcode: int, offset: int, length: int, limit: int) -> None:
        super().__init__(
            f"the {_kind(opcode)} record at byte {offset:,} is {length:,} bytes long, past the "
            f"{limit:,} bytes rlutf reads in one record (a log the service writes has records "
            "of about a megabyte, a map at most max_map_bytes)"
        )
        self.offset, self.length = offset, length


class RecordOverrun(RecordError):
    """A field of a record that runs past the record's end: its lengths cannot be trusted."""

    def __init__(self, opcode: int, offset: int, length: int) -> None:
        super().__init__(
            f"the {_kind(opcode)} record at byte {offset:,} is {length:,} bytes long, but a "
            "field of it runs past its end (the lengths in it cannot be trusted)"
        )


class RecordCut(RecordError):
    """A record that runs past the end of the file, or a file that ends before its footer."""


class _Crc:
    def __init__(self) -> None:
        self.value = 0

    def add(self, data: bytes) -> bytes:
        self.value = zlib.crc32(data, self.value)
        return data


class _Window(ReadDataStream):
    """A record's bytes, as the library's ``read`` methods read them: no more than its length."""

    def __init__(
        self, stream: IO[bytes], opcode: int, offset: int, length: int, crc: _Crc | None
    ) -> None:
        super().__init__(stream)
        self._opcode, self._offset, self._length = opcode, offset, length
        self.left = length
        self._sum = crc

    def read(self, length: int) -> bytes:
        if not 0 <= length <= self.left:
            raise RecordOverrun(self._opcode, self._offset, self._length)
        data = super().read(length)
        if len(data) != length:
            raise RecordCut(f"the file ends inside the record at byte {self._offset:,}")
        self.left -= length
        return self._sum.add(data) if self._sum is not None else data


def _size(stream: IO[bytes]) -> int:
    try:
        return os.fstat(stream.fileno()).st_size
    except (AttributeError, OSError, io.UnsupportedOperation):
        at = stream.tell()
        size = stream.seek(0, io.SEEK_END)
        stream.seek(at)
        return size


def _skip(stream: IO[bytes], length: int, crc: _Crc | None) -> None:
    if crc is None:
        stream.seek(length, io.SEEK_CUR)
        return
    while length > 0:  # read for the data section's CRC, a piece at a time
        piece = stream.read(min(length, _PIECE))
        if not piece:
            raise RecordCut("the file ends inside a record")
        crc.add(piece)
        length -= len(piece)


def read_records(
    stream: IO[bytes],
    wanted: Collection[int] | None = None,
    *,
    magic: bool = False,
    end: int | None = None,
    data_crc: bool = False,
    limit: int = MAX_RECORD_BYTES,
) -> Iterator[tuple[int, McapRecord]]:
    """The records from the stream's position on, each with the offset it starts at, to the
    footer (given, if wanted, and the last: the closing magic is checked after it) or ``end``.

    Args:
        wanted: the opcodes of the records to read; others are skipped, not read (all known
            ones are read if ``None``; a record of an unknown opcode is always skipped).
        magic: the stream is at the start of the file: check the MCAP magic first.
        end: stop at the first record that starts at or after this offset.
        data_crc: check a data end record's CRC over what came before it (with ``magic``).
        limit: the longest record read, bytes.

    Raises:
        RecordTooLarge: a record past ``limit`` that would be read.
        RecordOverrun: a field of a record runs past its end.
        RecordCut: a record runs past the end of the file, or the file ends before its footer
            and the closing magic.
        RecordError: no record can start here (opcode 0, reserved), or a data end's CRC does not
            match, or the magic is not there.
        Exception: whatever the library's record classes raise on a field (a bad UTF-8 string).
    """
    size = _size(stream)
    crc = _Crc() if data_crc and magic else None
    if magic:
        if stream.read(len(MAGIC)) != MAGIC:
            raise RecordError("the file does not start with the MCAP magic")
        if crc is not None:
            crc.add(MAGIC)
    while True:
        at = stream.tell()
        if end is not None and at >= end:
            return
        before = crc.value if crc is not None else 0
        head = stream.read(_HEAD)
        if len(head) < _HEAD:
            raise RecordCut(f"the file ends at byte {at + len(head):,}, before its footer")
        opcode, length = head[0], int.from_bytes(head[1:], "little")
        if opcode == 0:
            raise RecordError(f"at byte {at:,}, opcode 0x00, which no record has (0 is reserved)")
        if head.startswith(MAGIC):
            raise RecordError(
                f"at byte {at:,}, the magic that starts an MCAP file: the file holds more than one "
                "MCAP file (files concatenated?); give each log as its own file"
            )
        if crc is not None:
            crc.add(head)
        record_type = _RECORDS.get(opcode)
        read = record_type is not None and (
            wanted is None or opcode in wanted or opcode in (Opcode.FOOTER, Opcode.DATA_END)
        )
        if read and length > limit:
            raise RecordTooLarge(opcode, at, length, limit)
        if at + _HEAD + length > size:
            raise RecordCut(
                f"the {_kind(opcode)} record at byte {at:,} is {length:,} bytes long, past the "
                f"end of the file ({size:,} bytes)"
            )
        if record_type is None or not read:
            _skip(stream, length, crc)
            continue
        if length <= _SMALL:  # read in one piece: most records are small
            body = stream.read(length)
            window = _Window(io.BytesIO(crc.add(body) if crc else body), opcode, at, length, None)
        else:
            window = _Window(stream, opcode, at, length, crc)
        if record_type is Message:
            record = Message.read(window, length)
        else:
            record = record_type.read(window)  # type: ignore[attr-defined]
        if length > _SMALL:
            _skip(stream, window.left, crc)  # padding: fields a later version may add
        written = record.data_section_crc if isinstance(record, DataEnd) else 0  # 0: none
        if crc is not None and written not in (0, before):
            raise RecordError(
                f"the data section fails its CRC (recorded {written:#010x}, "
                f"computed {before:#010x})"
            )
        if isinstance(record, Footer):
            if wanted is None or Opcode.FOOTER in wanted:
                yield at, record
            if stream.read(len(MAGIC)) != MAGIC:
                raise RecordCut("the file does not end with the MCAP magic after its footer")
            return
        if wanted is None or opcode in wanted:
            yield at, record


def record_at(stream: IO[bytes], offset: int) -> McapRecord | None:
    """The record that starts at ``offset`` (``None`` for one of an unknown opcode).

    Raises:
        RecordError: as :func:`read_records`.
    """
    stream.seek(offset)
    for _, record in read_records(stream, end=offset + 1):
        return record
    return None


def read_header(stream: IO[bytes]) -> Header:
    """A file's header record.

    Raises:
        RecordError: the file does not start with the magic and a header, or it is unreadable.
    """
    stream.seek(0)
    for _, record in read_records(stream, magic=True, end=len(MAGIC) + 1):
        if isinstance(record, Header):
            return record
    raise RecordError("the file does not start with a header record")


def read_summary(stream: IO[bytes]) -> Summary | None:
    """A file's summary: the schemas, channels, statistics, chunk and metadata indexes between
    where its footer says the summary starts and the footer; ``None`` for a file without one.

    Raises:
        RecordError: no footer before the closing magic, or an unreadable summary record.
    """
    size = _size(stream)
    at = size - len(MAGIC) - _FOOTER
    footer = record_at(stream, at) if at >= len(MAGIC) else None
    if not isinstance(footer, Footer):
        raise RecordError(f"no footer record at byte {max(at, 0):,}, before the closing magic")
    if footer.summary_start == 0:
        return None
    summary = Summary()
    stream.seek(footer.summary_start)
    for offset, record in read_records(stream, SUMMARY_RECORDS | {Opcode.FOOTER}, end=at):
        if isinstance(record, Footer):  # another file's end, then more: files put together
            raise RecordError(
                f"a footer and the closing magic at byte {offset:,}, before the file's own at "
                f"byte {at:,}: the file holds more than one MCAP file (files concatenated?); "
                "give each log as its own file"
            )
        if isinstance(record, Statistics):
            summary.statistics = record
        elif isinstance(record, Schema):
            summary.schemas[record.id] = record
        elif isinstance(record, Channel):
            summary.channels[record.id] = record
        elif isinstance(record, ChunkIndex):
            summary.chunk_indexes.append(record)
        elif isinstance(record, MetadataIndex):
            summary.metadata_indexes.append(record)
    return summary


def read_metadata(stream: IO[bytes], summary: Summary | None) -> Iterator[Metadata]:
    """A file's metadata records: those its summary indexes, or, without a summary, every one
    met reading it through (chunks and other records skipped).

    Raises:
        RecordError: a metadata index that points at no metadata record, or as
            :func:`read_records`.
    """
    if summary is None:
        stream.seek(len(MAGIC))
        for _, record in read_records(stream, {Opcode.METADATA}):
            assert isinstance(record, Metadata)
            yield record
        return
    for index in summary.metadata_indexes:
        found = record_at(stream, index.offset)
        if not isinstance(found, Metadata):
            raise RecordError(
                f"the metadata index {index.name!r} points at byte {index.offset:,}, where no "
                "metadata record starts"
            )
        yield found


def bound_file(path: Path) -> None:
    """Check the records and chunks of an MCAP file that rosbags reads whole (to the length they
    declare; a chunk decompressed whole, as the ``mcap`` library does) against the bounds
    before it reads them, a record at a time: all but the attachments and metadata records it
    skips. A file that is not MCAP, or whose records stop making sense, is left to rosbags to
    name.

    Raises:
        ChunkTooLarge: a chunk past :data:`~service.logs.mcapchunks.MAX_CHUNK_BYTES`.
        RecordTooLarge: a record past :data:`MAX_RECORD_BYTES`.
        OSError: the file cannot be opened, or is not a regular file.
    """
    with open_regular(path) as stream:
        try:
            for _, record in read_records(stream, _ROSBAGS_READS, magic=True):
                if isinstance(record, Chunk):
                    inflated_size(record)
        except (ChunkTooLarge, RecordTooLarge):
            raise
        except Exception:  # damaged past here: the bag's reader says so in its own words
            return
