"""``rlutf log recover``: a damaged or cut-short MCAP file copied into a new, complete one
(:func:`recover`).

Recovery reads the damaged file front to back, a record at a time within the bound of
:func:`service.logs.mcaprecords.read_records` (a record past it is an unreadable one), and
copies every record of every complete chunk (schemas, channels, messages) and every metadata and
attachment record into a new, complete file. A chunk that fails its CRC or does not decompress
is skipped and counted. Where a record is unreadable (a corrupted length, garbage), reading
resumes at the next chunk that checks out (its CRC over its decompressed records) or metadata
record (:func:`next_readable`: found by trying each byte that is such a record's opcode), so one
damaged record costs only itself; it stops where the file is cut short. A chunk that repeats an
earlier one byte for byte (a copy written twice) is copied once.

The copy ends with an ``rlutf.recovered`` metadata record (:mod:`service.logs.manifest`) that
says what it lacks: the damaged chunks, unreadable stretches and messages whose channel record
was lost, and where the input was cut short; a channel whose schema record was lost is copied
without a schema. Readers of the copy count and name both, so that an audit of it never passes
over what it could not read.

A file that declares a channel or schema id twice, differently, is refused, as the readers refuse
it (:class:`~service.logs.mcapread.RedeclaredLog`): copied, the messages on that id would all be
filed under its first declaration, and the output would read as a valid log with some messages
on the wrong topic.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.records import Attachment, Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from service.infile import open_regular
from service.logs.manifest import RECOVERED_METADATA, Recovered
from service.logs.mcapchunks import unpack_chunk
from service.logs.mcaporder import Declarations, Redeclared
from service.logs.mcapread import MAGIC, NotALog, RedeclaredLog
from service.logs.mcaprecords import read_records, record_at

#: The opcodes of the records reading may resume at after an unreadable stretch: a chunk's or a
#: metadata record's.
_RESUMABLE = (b"\x06", b"\x0c")
_SCAN_BLOCK = 1 << 20
_METADATA_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def _resumable(src: IO[bytes], at: int) -> bool:
    """Whether a chunk that checks out, or a metadata record, starts at ``at``."""
    try:
        record = record_at(src, at)  # bounded: a length past the file or the bound is refused
        if isinstance(record, Chunk):
            unpack_chunk(record)
            return record.uncompressed_crc != 0  # a CRC was written: it is what checked out
        return isinstance(record, Metadata) and _METADATA_NAME.fullmatch(record.name) is not None
    except Exception:
        return False


def _candidates(block: bytes) -> Iterator[int]:
    """Where ``block`` holds an opcode of :data:`_RESUMABLE`, in order (found at memchr speed: a
    stretch of zeros, a sparse file's hole, costs little more than reading it)."""
    ahead = {opcode: block.find(opcode) for opcode in _RESUMABLE}
    while found := [(at, opcode) for opcode, at in ahead.items() if at >= 0]:
        at, opcode = min(found)
        yield at
        ahead[opcode] = block.find(opcode, at + 1)


def next_readable(src: IO[bytes], start: int, size: int) -> int | None:
    """The offset of the next record at or after ``start`` that reading may resume at."""
    pos = start
    while pos < size:
        src.seek(pos)
        block = src.read(_SCAN_BLOCK)
        for at in _candidates(block):
            if _resumable(src, pos + at):
                return pos + at
        pos += len(block)
    return None


@dataclass
class RecoverReport:
    """What :func:`recover` salvaged.

    Attributes:
        messages: messages copied.
        chunks: complete chunks copied.
        bad_chunks: chunks skipped (CRC mismatch or not decompressible).
        duplicate_chunks: chunks skipped as byte-for-byte repeats of an earlier chunk.
        resyncs: unreadable stretches skipped to the next readable chunk or metadata record.
        first_unreadable: byte offset of the first unreadable stretch, if any.
        first_problem: what was wrong there.
        lost_messages: messages skipped because their channel record was lost.
        metadata: metadata records copied.
        complete: the input's footer was reached (nothing was missing).
        stopped: why reading stopped before the footer, if it did.
        stopped_at: byte offset where it stopped.
    """

    messages: int = 0
    chunks: int = 0
    bad_chunks: int = 0
    duplicate_chunks: int = 0
    resyncs: int = 0
    first_unreadable: int | None = None
    first_problem: str | None = None
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
        self.declared = Declarations()  # every declaration met, data section and summary

    def start(self, header: Header | None) -> None:
        if not self.started:
            self.started = True
            self.writer.start(
                profile=header.profile if header else "",
                library=header.library if header else "rlutf recover",
            )

    def take(self, rec: Any) -> None:
        """Copy a record (a schema or channel only the first time its id is met).

        Raises:
            Redeclared: a schema or channel id met before as something else.
        """
        self.declared.add(rec)
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
    size = os.fstat(src.fileno()).st_size
    seen: set[bytes] = set()
    at, first = 0, True
    while True:
        src.seek(at)
        end = at if not first else len(MAGIC)
        try:
            for _, rec in read_records(src, magic=first):
                if isinstance(rec, Header):
                    copier.start(rec)
                    end = src.tell()
                    continue
                copier.start(None)
                if isinstance(rec, Chunk):
                    digest = hashlib.sha256(rec.data).digest() + rec.message_start_time.to_bytes(
                        8, "little"
                    )
                    if digest in seen:
                        report.duplicate_chunks += 1
                        end = src.tell()
                        continue
                    try:
                        inner = unpack_chunk(rec)
                    except Exception:  # bad CRC or compression: skip this chunk only
                        report.bad_chunks += 1
                        end = src.tell()
                        continue
                    seen.add(digest)
                    for item in inner:
                        copier.take(item)
                    report.chunks += 1
                elif isinstance(rec, Footer):
                    report.complete = True
                else:
                    copier.take(rec)
                end = src.tell()
            if report.complete and src.tell() < size:  # another file appended (`cat a b`)
                report.complete = False
                report.stopped_at = src.tell()
                report.stopped = (
                    f"{size - src.tell():,} more bytes after its footer and closing magic, not "
                    "read: another file appended? recover it on its own"
                )
            break
        except Redeclared:
            raise
        except Exception as err:  # the cut, or garbage where a record should start
            problem = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
            resume = next_readable(src, end + 1, size)
            if resume is None:
                report.stopped, report.stopped_at = problem, end
                break
            if report.first_unreadable is None:
                report.first_unreadable, report.first_problem = end, problem
            report.resyncs += 1
            at, first = resume, False
    copier.start(None)


def _record(src: Path, report: RecoverReport) -> Recovered:
    """What the copy lacks, for its readers (:mod:`service.logs.manifest`)."""
    return Recovered(
        src.name,
        report.complete,
        None if report.complete else report.stopped_at,
        report.bad_chunks,
        report.resyncs,
        report.lost_messages,
    )


def recover(src: Path, dst: Path) -> RecoverReport:
    """Copy everything readable of ``src`` into a new complete log ``dst``.

    Raises:
        NotALog: ``src`` is missing or not MCAP, or ``dst`` is ``src``.
        RedeclaredLog: ``src`` declares a channel or schema id twice, differently (nothing is
            written).
    """
    if dst.exists() and dst.resolve() == src.resolve():
        raise NotALog(f"{dst}: the output must not be the input")
    try:
        stream = open_regular(src)  # closed below
    except OSError as err:
        raise NotALog(f"{src}: cannot open: {err.strerror or err}") from err
    with stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise NotALog(f"{src}: not an MCAP file (it does not start with the MCAP magic)")
        stream.seek(0)
        report = RecoverReport()
        part = dst.with_name(dst.name + ".part")
        if part.exists() and part.resolve() == src.resolve():  # `recover X.mcap.part X.mcap`
            part = dst.with_name(f".{dst.name}.recovering")  # not the input, which it truncated
        try:
            with open(part, "wb") as out:
                writer = Writer(out, compression=CompressionType.ZSTD)
                try:
                    _copy(stream, writer, report)
                except Redeclared as err:
                    raise RedeclaredLog(src, str(err)) from err
                writer.add_metadata(RECOVERED_METADATA, _record(src, report).to_metadata())
                writer.finish()
                out.flush()
                os.fsync(out.fileno())
        except BaseException:
            part.unlink(missing_ok=True)
            raise
    os.replace(part, dst)
    return report
