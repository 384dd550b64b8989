"""A record is read only within the bound, whatever length it or a field of it declares.

The ``mcap`` library read any record whole, up to 4 GiB, and trusted the lengths inside it: a
12 KB sparse file whose one attachment, message, metadata or schema record declares 513 MiB took
513 MiB to 1 GiB to read and 1.5 GiB to ``rlutf log recover``; a message record shorter than
its fixed fields, or a chunk whose data length runs past its record, read the rest of the file.
The files here are real and complete, sparse (a hole of 513 MiB of zeros: a few kilobytes on
disk); read bounded, a few megabytes are held.
"""

from __future__ import annotations

import io
import json
import struct
import tracemalloc
import zlib
from pathlib import Path

import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MetadataIndex,
    Schema,
    Statistics,
)

from service.cli.main import main
from service.logs.mcapchunks import MAX_CHUNK_BYTES
from service.logs.mcapread import DamagedLog, LogFile
from service.logs.mcaprecords import (
    MAX_RECORD_BYTES,
    RecordOverrun,
    RecordTooLarge,
    read_records,
)
from service.logs.salvage import recover

MAGIC = b"\x89MCAP0\r\n"
HUGE = MAX_RECORD_BYTES + (1 << 20)  # the zeros a huge record declares past its fields
PEAK = 16 << 20  # what reading any of these files may hold, bytes
SCHEMA = Schema(id=1, name="rlutf.Event", encoding="jsonschema", data=b"{}")
CHANNEL = Channel(
    id=1, topic="rlutf/robots/r1/events", message_encoding="json", schema_id=1, metadata={}
)


def _records(*records: object) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)  # type: ignore[attr-defined]
    return bytes(builder.end())


def _chunk(*records: object, t: int) -> Chunk:
    data = _records(*records)
    return Chunk(
        compression="",
        data=data,
        message_end_time=t,
        message_start_time=t,
        uncompressed_crc=zlib.crc32(data),
        uncompressed_size=len(data),
    )


def _event(t: int) -> Message:
    return Message(channel_id=1, sequence=0, log_time=t, publish_time=t, data=b'{"n": %d}' % t)


def _head(opcode: int, length: int, fields: bytes = b"") -> bytes:
    return struct.pack("<BQ", opcode, length) + fields


def _huge(kind: str) -> tuple[bytes, int]:
    """What is written of the huge record (its head and first fields), and how many zero bytes
    follow (left as a hole)."""
    unknown = _head(0x80, HUGE)  # a record of an opcode no reader knows
    if kind == "attachment":  # log time, create time, name, media type, data: HUGE zeros, crc
        fields = struct.pack("<QQI", 0, 0, 3) + b"big" + struct.pack("<I", 0)
        fields += struct.pack("<Q", HUGE)
        return _head(0x09, len(fields) + HUGE + 4, fields), HUGE + 4
    if kind == "unknown record":
        return unknown, HUGE
    if kind == "message":  # a message whose data is HUGE zeros
        fields = struct.pack("<HIQQ", 1, 0, 1500, 1500)
        return _head(0x05, len(fields) + HUGE, fields), HUGE
    if kind == "metadata":  # a name, then a map of one key and a value of HUGE zeros
        fields = struct.pack("<I", 4) + b"note" + struct.pack("<II", HUGE + 9, 1) + b"k"
        fields += struct.pack("<I", HUGE)
        return _head(0x0C, len(fields) + HUGE, fields), HUGE
    if kind == "schema padding":  # a schema with HUGE zeros after its fields
        fields = struct.pack("<HI", 2, 1) + b"x" + struct.pack("<I", 1) + b"j"
        fields += struct.pack("<I", 2) + b"{}"
        return _head(0x03, len(fields) + HUGE, fields), HUGE
    if kind == "short message":  # 21 bytes long, one short of a message's fixed fields
        fields = struct.pack("<HIQ", 1, 0, 1500) + bytes(7)
        return _head(0x05, len(fields), fields) + unknown, HUGE
    if kind == "chunk overrun":  # a chunk whose data length says HUGE, its record 40 bytes
        fields = struct.pack("<QQQII", 1000, 1000, 0, 0, 0) + struct.pack("<Q", HUGE)
        return _head(0x06, len(fields), fields) + unknown, HUGE
    raise ValueError(kind)


def _hostile(path: Path, kind: str, layout: str) -> Path:
    """magic, header, a chunk (schema, channel, an Event at 1000), the huge record, a chunk (an
    Event at 2000), data end, a summary (``layout`` "indexed": chunk indexes, statistics, an
    index of the huge record if it is metadata; "summary": the huge record in it), footer,
    magic."""
    head, zeros = _huge(kind)
    chunks = [_chunk(SCHEMA, CHANNEL, _event(1000), t=1000), _chunk(_event(2000), t=2000)]
    with open(path, "wb") as out:
        out.write(MAGIC + _records(Header(profile="", library="hostile")))
        at = [out.tell()]
        out.write(_records(chunks[0]))
        huge_at = out.tell()
        if layout != "summary":
            out.write(head)
            out.seek(zeros, io.SEEK_CUR)
        at.append(out.tell())
        out.write(_records(chunks[1]))
        out.write(_records(DataEnd(data_section_crc=0)))
        summary_at = out.tell() if layout != "no summary" else 0
        if layout == "summary":
            out.write(_records(SCHEMA, CHANNEL))
            out.write(head)
            out.seek(zeros, io.SEEK_CUR)
        elif layout == "indexed":
            out.write(_records(SCHEMA, CHANNEL, *_index(chunks, at)))
            if kind == "metadata":
                length = len(head) + zeros
                out.write(_records(MetadataIndex(offset=huge_at, length=length, name="note")))
        footer = Footer(summary_start=summary_at, summary_offset_start=0, summary_crc=0)
        out.write(_records(footer) + MAGIC)
    return path


def _index(chunks: list[Chunk], at: list[int]) -> list[object]:
    stats = Statistics(
        attachment_count=0,
        channel_count=1,
        channel_message_counts={1: 2},
        chunk_count=2,
        message_count=2,
        message_end_time=2000,
        message_start_time=1000,
        metadata_count=0,
        schema_count=1,
    )
    return [
        stats,
        *(
            ChunkIndex(
                chunk_length=len(_records(chunk)),
                chunk_start_offset=offset,
                compression="",
                compressed_size=len(chunk.data),
                message_end_time=chunk.message_end_time,
                message_index_length=0,
                message_index_offsets={},
                message_start_time=chunk.message_start_time,
                uncompressed_size=chunk.uncompressed_size,
            )
            for chunk, offset in zip(chunks, at, strict=True)
        ),
    ]


REFUSED_PAST_THE_BOUND = "record at byte {at:,} is {length:,} bytes long, past the {limit:,} bytes"
OVERRUN = "record at byte {at:,} is {length:,} bytes long, but a field of it runs past its end"
CASES = [
    # kind, layout, what the readers say (None: they read both Events), recover's resyncs
    ("attachment", "no summary", None, 1),  # never used by the readers: not read
    ("attachment", "indexed", None, 1),
    ("unknown record", "no summary", None, 0),
    ("message", "no summary", ("Message", REFUSED_PAST_THE_BOUND, HUGE + 22), 1),
    ("metadata", "no summary", ("Metadata", REFUSED_PAST_THE_BOUND, HUGE + 21), 1),
    ("metadata", "indexed", ("Metadata", REFUSED_PAST_THE_BOUND, HUGE + 21), 1),
    ("schema padding", "no summary", ("Schema", REFUSED_PAST_THE_BOUND, HUGE + 18), 1),
    ("schema padding", "summary", ("Schema", REFUSED_PAST_THE_BOUND, HUGE + 18), 0),
    ("short message", "no summary", ("Message", OVERRUN, 21), 1),
    ("chunk overrun", "no summary", ("Chunk", OVERRUN, 40), 1),
]


@pytest.mark.parametrize(
    ("kind", "layout", "refusal", "resyncs"), CASES, ids=[f"{c[0]}, {c[1]}" for c in CASES]
)
def test_a_record_past_the_bound_is_neither_read_nor_held(
    kind: str,
    layout: str,
    refusal: tuple[str, str, int] | None,
    resyncs: int,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = _hostile(tmp_path / "hostile.mcap", kind, layout)
    assert path.stat().st_size > HUGE and path.stat().st_blocks * 512 < 1 << 20
    refused = None
    tracemalloc.start()
    try:
        try:
            with LogFile(path) as log:
                read = [json.loads(r.payload)["n"] for r in log.messages()]
                log.metadata()
        except DamagedLog as err:
            refused = str(err)
        report = recover(path, tmp_path / "fixed.mcap")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < PEAK, f"{peak:,} bytes held"
    if refusal is None:
        assert refused is None and read == [1000, 2000], refused
    else:
        name, words, length = refusal
        at = path.stat().st_size - len(MAGIC) - 29 - 9 - length if layout == "summary" else 220
        said = words.format(at=at, length=length, limit=MAX_RECORD_BYTES)
        assert refused is not None and str(path) in refused, refused
        assert f"the {name} {said}" in refused, refused
    # recover copies both chunks, past the huge record (an unreadable stretch, or skipped)
    assert report.messages == 2 and report.resyncs == resyncs, report
    if resyncs:
        assert report.first_unreadable == 220 and "record at byte 220" in str(report.first_problem)
    with LogFile(tmp_path / "fixed.mcap") as fixed:
        assert [json.loads(r.payload)["n"] for r in fixed.messages()] == [1000, 2000]
    assert main(["log", "info", str(path)]) == (0 if refusal is None else 2)
    err = capsys.readouterr().err
    assert "Traceback" not in err and (refusal is None or "past" in err), err


def test_the_bound_holds_a_chunk_at_the_chunk_bound_and_refuses_one_byte_more() -> None:
    """The bound is the chunk bound's, with room for a chunk record's own fields: so a chunk of
    MAX_CHUNK_BYTES fits it. At a limit of 1,000 bytes, a chunk record of 1,000 is read, one of
    1,001 refused."""
    fields = len(_records(_chunk(t=0))) - 9  # a chunk record's length besides its data
    assert MAX_CHUNK_BYTES + fields + len("zstd") <= MAX_RECORD_BYTES
    for length in (1000, 1001):
        data = b"x" * (length - fields)
        record = _records(Chunk("", data, 0, 0, 0, len(data)))
        assert len(record) == 9 + length
        stream = io.BytesIO(record + _records(Footer(0, 0, 0)) + MAGIC)
        if length == 1000:
            assert [type(r) for _, r in read_records(stream, limit=1000)] == [Chunk, Footer]
        else:
            with pytest.raises(RecordTooLarge, match="Chunk record at byte 0 is 1,001 bytes"):
                list(read_records(stream, limit=1000))


def test_a_field_past_its_record_is_refused_not_read_on() -> None:
    """A schema whose data length says more than its record holds: the library read on into
    the records after it."""
    schema = _records(Schema(id=1, name="s", encoding="e", data=b"{}"))
    lying = schema[:-6] + struct.pack("<I", 1 << 30) + schema[-2:]  # data length 1 GiB
    stream = io.BytesIO(lying + _records(Footer(0, 0, 0)) + MAGIC)
    said = "Schema record at byte 0 is 18 bytes long, but a field of it runs past its end"
    with pytest.raises(RecordOverrun, match=said):
        list(read_records(stream))


def test_a_rosbag2_mcap_with_a_record_past_the_bound_is_refused_before_rosbags_reads_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rosbags reads a record whole to the length it declares, as the ``mcap`` library does: a
    12 KB bag whose one schema record declares 513 MiB took 575 MB to ``rlutf map build
    --ros2``, which then said its scans had no poses."""
    head, zeros = _huge("schema padding")
    bag = tmp_path / "bag.mcap"
    with open(bag, "wb") as out:
        out.write(MAGIC + _records(Header(profile="ros2", library="hostile")) + head)
        out.seek(zeros, io.SEEK_CUR)
        out.write(_records(DataEnd(data_section_crc=0), Footer(0, 0, 0)) + MAGIC)
    room = {"type": "Polygon", "coordinates": [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]]}
    (tmp_path / "site.json").write_text(json.dumps({"map_id": "site", "geometry": room}))
    tracemalloc.start()
    try:
        code = main(["map", "build", "--ros2", str(bag), "--out", str(tmp_path / "m.json")])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    err = capsys.readouterr().err
    assert code == 2 and "not a readable rosbag2 recording" in err, err
    assert "the Schema record at byte 36 is" in err and "past the" in err, err
    assert peak < 64 << 20, f"{peak:,} bytes held"  # map build --ros2 alone holds about 35 MB
