"""A chunk that decompresses to more than rlutf reads in one chunk is refused, a piece at a time,
before it is held whole. The ``mcap`` library decompresses a chunk whole to what its frame
declares: a 33 KB file with one chunk of a gigabyte of spaces took 2.1 GB to ``rlutf log info``,
and zstd's ratio lets a 1 MB file ask for 30 GB (the OOM killer, on a host the service shares).
Here the chunk holds a little more than the bound, :data:`MAX_CHUNK_BYTES`, so that the test is
cheap: read whole it would be 513 MiB, bounded the reads hold a few megabytes."""

from __future__ import annotations

import io
import json
import struct
import tracemalloc
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import lz4.frame  # type: ignore[import-untyped]
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Schema,
    Statistics,
)

from service.cli.main import main
from service.logs.mcapchunks import MAX_CHUNK_BYTES, ChunkTooLarge, inflated_size
from service.logs.mcapread import DamagedLog, LogFile
from service.logs.salvage import recover

MAGIC = b"\x89MCAP0\r\n"
PAD = MAX_CHUNK_BYTES + (1 << 20)  # bytes of JSON whitespace in the one message
PIECE = b" " * (1 << 20)


def _records(*records: object) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)  # type: ignore[attr-defined]
    return bytes(builder.end())


def _inner(ros2: bool = False) -> tuple[bytes, bytes, int]:
    """The chunk's records: a schema and a channel, then the head of a message whose data (PAD
    spaces and ``{}``) follows; and their size."""
    head = _records(
        Schema(id=1, name="sensor_msgs/msg/LaserScan", encoding="ros2msg", data=b"")
        if ros2
        else Schema(id=1, name="rlutf.Event", encoding="jsonschema", data=b"{}"),
        Channel(id=1, topic="/scan", message_encoding="cdr", schema_id=1, metadata={})
        if ros2
        else Channel(
            id=1, topic="rlutf/robots/r1/events", message_encoding="json", schema_id=1, metadata={}
        ),
    )
    data_len = PAD + 2
    message = struct.pack("<BQHIQQ", 5, 2 + 4 + 8 + 8 + data_len, 1, 0, 1000, 1000)
    return head, message, len(head) + len(message) + data_len


def _zstd(content_size: bool, ros2: bool = False) -> tuple[bytes, int]:
    head, message, size = _inner(ros2)
    out = io.BytesIO()
    compressor = zstandard.ZstdCompressor(level=1, write_content_size=content_size)
    with compressor.stream_writer(out, size=size if content_size else -1, closefd=False) as w:
        w.write(head + message)
        for _ in range(PAD // len(PIECE)):
            w.write(PIECE)
        w.write(b"{}")
    return out.getvalue(), size


def _lz4() -> tuple[bytes, int]:
    head, message, size = _inner()
    compressor = lz4.frame.LZ4FrameCompressor()
    parts = [compressor.begin(), compressor.compress(head + message)]
    parts += [compressor.compress(PIECE) for _ in range(PAD // len(PIECE))]
    parts += [compressor.compress(b"{}"), compressor.flush()]
    return b"".join(parts), size


def _bomb(
    path: Path, compression: str, data: bytes, declared: int, indexed: bool, profile: str = ""
) -> Path:
    """A complete MCAP file with that one chunk; with ``indexed``, a summary that indexes it."""
    chunk = Chunk(
        compression=compression,
        data=data,
        message_end_time=1000,
        message_start_time=1000,
        uncompressed_crc=0,
        uncompressed_size=declared,
    )
    start = _records(Header(profile=profile, library="a bomb"))
    body = _records(chunk)
    out = MAGIC + start
    chunk_at = len(out)
    out += body + _records(DataEnd(data_section_crc=0))
    summary = b""
    if indexed:
        summary = _records(
            Schema(id=1, name="rlutf.Event", encoding="jsonschema", data=b"{}"),
            Channel(
                id=1,
                topic="rlutf/robots/r1/events",
                message_encoding="json",
                schema_id=1,
                metadata={},
            ),
            Statistics(
                attachment_count=0,
                channel_count=1,
                channel_message_counts={1: 1},
                chunk_count=1,
                message_count=1,
                message_end_time=1000,
                message_start_time=1000,
                metadata_count=0,
                schema_count=1,
            ),
            ChunkIndex(
                chunk_length=len(body),
                chunk_start_offset=chunk_at,
                compression=compression,
                compressed_size=len(data),
                message_end_time=1000,
                message_index_length=0,
                message_index_offsets={},
                message_start_time=1000,
                uncompressed_size=declared,
            ),
        )
    summary_at = len(out) if indexed else 0
    out += (
        summary
        + _records(Footer(summary_start=summary_at, summary_offset_start=0, summary_crc=0))
        + MAGIC
    )
    path.write_bytes(out)
    return path


Maker = Callable[[Path, bool], Path]


def _zstd_file(path: Path, indexed: bool) -> Path:
    data, size = _zstd(content_size=True)
    return _bomb(path, "zstd", data, size, indexed)


def _zstd_lying(path: Path, indexed: bool) -> Path:
    data, _ = _zstd(content_size=False)  # no size in the frame, and the chunk says 1 KB
    return _bomb(path, "zstd", data, 1024, indexed)


def _lz4_lying(path: Path, indexed: bool) -> Path:
    data, _ = _lz4()
    return _bomb(path, "lz4", data, 1024, indexed)


@pytest.mark.parametrize("indexed", [True, False], ids=["indexed", "no summary"])
@pytest.mark.parametrize("make", [_zstd_file, _zstd_lying, _lz4_lying])
def test_a_chunk_past_the_bound_is_refused_without_being_held(
    make: Maker, indexed: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = make(tmp_path / "bomb.mcap", indexed)
    assert path.stat().st_size < 5_000_000
    tracemalloc.start()
    try:
        with pytest.raises(DamagedLog, match="past the"), LogFile(path) as log:
            sum(1 for _ in log.messages())
        report = recover(path, tmp_path / "fixed.mcap")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, f"{peak:,} bytes held"
    assert report.bad_chunks == 1 and report.messages == 0
    for argv in (["log", "info", str(path)], ["replay", str(path), "--quiet", "--jobs", "1"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "past the" in err and "Traceback" not in err, err


def test_a_chunk_within_the_bound_is_counted_whatever_it_declares() -> None:
    data = zstandard.ZstdCompressor(write_content_size=False).compress(b"x" * 5000)
    chunk = Chunk(
        compression="zstd",
        data=data,
        message_end_time=0,
        message_start_time=0,
        uncompressed_crc=0,
        uncompressed_size=10,
    )
    assert inflated_size(chunk) == 5000
    with pytest.raises(ChunkTooLarge, match="decompresses to"):
        inflated_size(chunk, limit=4096)
    lz4_chunk = replace(chunk, compression="lz4", data=lz4.frame.compress(b"x" * 5000))
    assert inflated_size(lz4_chunk) == 5000
    with pytest.raises(ChunkTooLarge, match="declares"):
        inflated_size(lz4_chunk, limit=4096)  # the lz4 frame says 5000


def test_a_rosbag2_mcap_with_a_chunk_past_the_bound_is_refused_before_rosbags_reads_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--ros2`` reads a bag with rosbags, which decompresses a chunk whole too: a 17 KB bag
    took 1.1 GB to ``rlutf replay --ros2`` and ``rlutf map build --ros2``."""
    data, size = _zstd(content_size=True, ros2=True)
    bag = _bomb(tmp_path / "bag.mcap", "zstd", data, size, indexed=False, profile="ros2")
    room = {"type": "Polygon", "coordinates": [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]]}
    (tmp_path / "site.json").write_text(json.dumps({"map_id": "site", "geometry": room}))
    pose = ["--map", str(tmp_path / "site.json"), "--initial-pose", "1,1,0"]
    tracemalloc.start()
    try:
        for argv, exit_code in (
            (["replay", "--ros2", str(bag), *pose, "--quiet"], 2),
            (["map", "build", "--ros2", str(bag), "--out", str(tmp_path / "m.json")], 2),
        ):
            assert main(argv) == exit_code
            err = capsys.readouterr().err
            assert "not a readable rosbag2 recording" in err and "past the" in err, err
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, f"{peak:,} bytes held"


def test_a_footer_that_starts_the_summary_at_a_chunk_is_bounded_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The ``mcap`` library reads a summary from where the footer says it starts up to the
    footer, and breaks up a chunk it meets there whole: a footer pointing its summary at the
    data section had ``LogFile`` decompress the chunk to 513 MiB before any bound was checked.
    The summary's reader skips chunks."""
    data, size = _zstd(content_size=True)
    path = _bomb(tmp_path / "bomb.mcap", "zstd", data, size, indexed=False)
    raw = bytearray(path.read_bytes())
    footer_at = len(raw) - len(MAGIC) - 29
    chunk_at = len(MAGIC) + len(_records(Header(profile="", library="a bomb")))
    raw[footer_at + 9 : footer_at + 17] = chunk_at.to_bytes(8, "little")  # summary start
    path.write_bytes(bytes(raw))
    tracemalloc.start()
    try:
        with pytest.raises(DamagedLog, match="past the"), LogFile(path) as log:
            sum(1 for _ in log.messages())
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, f"{peak:,} bytes held"
    assert main(["log", "info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "past the" in err and "Traceback" not in err, err
