"""A log's messages are read in log-time order holding a bounded part of it, whatever order the
file holds them in. A file without a chunk index (a crashed recording, or another tool's) whose
messages were out of order was sorted whole in memory: 23 MB held to read 20 MB of messages, 229
MB for ten times as many; and a file whose every chunk spans the whole log was read keeping every
chunk, index or not (a 0.5 MB file took 47 MB)."""

from __future__ import annotations

import json
import random
import tracemalloc
from pathlib import Path
from typing import Any

import pytest
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import Footer
from mcap.writer import IndexType
from mcap.writer import Writer as McapWriter
from mcaplog_fixtures import add_outside_chunks, unindex_last_chunk

from service.cli.main import main
from service.logs import mcaporder
from service.logs.mcapread import DamagedLog, LogFile, UnorderedLog

LAYOUTS: dict[str, dict[str, Any]] = {
    "indexed": {},
    "no chunk index": {"index_types": IndexType.NONE},
    "no summary": {
        "index_types": IndexType.NONE,
        "use_statistics": False,
        "use_summary_offsets": False,
        "repeat_channels": False,
        "repeat_schemas": False,
    },
    "unchunked": {"use_chunking": False},
    # indexed chunks and, beside them, every third message outside any chunk
    "outside chunks": {"outside": 3},
    # every other chunk left out of the chunk index
    "unindexed chunks": {"unindexed": 2},
}
PAYLOAD = json.dumps({"pad": "x" * 2000}).encode()


def _write(path: Path, times: list[int], layout: str, chunk_size: int = 200_000) -> Path:
    """A file by the ``mcap`` library's writer with a message at each of ``times``, in that order,
    on two channels in turn; each message's payload says where it is in the file."""
    options = dict(LAYOUTS[layout])
    outside, unindexed = options.pop("outside", 0), options.pop("unindexed", 0)
    with open(path, "wb") as out:
        writer = McapWriter(out, chunk_size=chunk_size, **options)
        writer.start("another writer", "")
        schema = writer.register_schema("rlutf.Event", "jsonschema", b"{}")
        channels = [
            writer.register_channel(f"rlutf/robots/r{i}/events", "json", schema) for i in (1, 2)
        ]
        for i, t in enumerate(times):
            payload = PAYLOAD if len(times) > 1000 else json.dumps({"at": i}).encode()
            if outside and i % outside == 0:
                add_outside_chunks(writer, channels[i % 2], t, payload, t)
            else:
                writer.add_message(channels[i % 2], t, payload, t)
            if unindexed and i % (unindexed * 40) == 0:
                unindex_last_chunk(writer)
        writer.finish()
    return path


def _peak_reading(path: Path) -> tuple[list[int], int]:
    """The log times of a file's messages as read, and the bytes held at most to read them."""
    with LogFile(path) as log:
        tracemalloc.start()
        try:
            times = [r.log_time_ns for r in log.messages()]
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    return times, peak


def _blocks_reversed(n: int, block: int) -> list[int]:
    """``n`` times written a block at a time, each block backwards: out of order a little."""
    return [1000 + i for b in range(0, n, block) for i in reversed(range(b, min(n, b + block)))]


@pytest.mark.parametrize(
    "layout", ["no summary", "unchunked", "outside chunks", "unindexed chunks"]
)
def test_a_log_without_a_chunk_index_out_of_order_is_read_holding_a_few_spans(
    layout: str, tmp_path: Path
) -> None:
    """20 MB of messages, each hundred written backwards: 23 MB held before, 1.6 MB now (and for
    ten times as many, 229 MB before, 1.5 MB now). So are those outside the indexed chunks of a
    file with a chunk index (which were not read at all)."""
    times = _blocks_reversed(10_000, 100)
    read, peak = _peak_reading(_write(tmp_path / "late.mcap", times, layout))
    assert read == sorted(times)
    assert peak < 4_000_000, f"{peak:,} bytes held to read 20 MB of messages"


@pytest.mark.parametrize("layout", ["indexed", "no summary"])
def test_a_log_whose_chunks_all_overlap_in_time_is_refused_before_it_is_read(
    layout: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each message written after one 100 steps later than it: every chunk spans the whole log,
    so putting it in order takes holding all of it. Past the bound (here 4 MB, to be quick) it is
    refused before a message is given, naming the file and how to sort it; it was read whole."""
    monkeypatch.setattr(mcaporder, "MAX_OPEN_BYTES", 4_000_000)
    n = 10_000
    path = _write(tmp_path / "spread.mcap", [1000 + (i % 100) * n + i for i in range(n)], layout)
    with LogFile(path) as log:
        tracemalloc.start()
        try:
            with pytest.raises(UnorderedLog, match="out of log-time order") as refused:
                next(log.messages())
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert str(path) in str(refused.value) and "mcap sort" in str(refused.value)
    assert peak < 6_000_000, f"{peak:,} bytes held"
    assert main(["log", "info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "out of log-time order" in err and "Traceback" not in err, err


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("seed", range(8))
def test_messages_are_read_in_log_time_then_file_order_whatever_the_layout(
    layout: str, seed: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The order the ``mcap`` library gives (stable sort by log time) whatever the spans: many
    equal times, messages late by up to 40 places, chunks and spans of a few messages."""
    monkeypatch.setattr(mcaporder, "SPAN_BYTES", 700)
    rng = random.Random(seed)
    times = [1000 + i // 3 + rng.choice((0, 0, -rng.randint(0, 40))) for i in range(400)]
    path = _write(tmp_path / "mixed.mcap", times, layout, chunk_size=rng.choice((300, 2000)))
    with LogFile(path) as log:
        read = [(r.log_time_ns, json.loads(r.payload)["at"], r.topic) for r in log.messages()]
    expected = sorted(range(len(times)), key=lambda i: times[i])
    assert read == [(times[i], i, f"rlutf/robots/r{1 + i % 2}/events") for i in expected]


def test_a_chunk_index_that_lies_about_its_times_is_damage(tmp_path: Path) -> None:
    """A chunk that holds messages outside the times its index declares would be read out of
    order, or held to the end: refused as damaged (``rlutf log recover`` indexes it anew)."""
    path = _write(tmp_path / "log.mcap", list(range(1000, 1400)), "indexed", chunk_size=2000)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    data = path.read_bytes()
    summary_start = int.from_bytes(data[-28:-20], "little")  # the footer's first field
    builder = RecordBuilder()
    for record in [*summary.schemas.values(), *summary.channels.values()]:
        record.write(builder)
    for k, index in enumerate(summary.chunk_indexes):
        if k == 1:
            index.message_start_time, index.message_end_time = 0, 0  # "its messages are at 0"
        index.write(builder)
    Footer(summary_start=summary_start, summary_offset_start=0, summary_crc=0).write(builder)
    liar = tmp_path / "liar.mcap"
    liar.write_bytes(data[:summary_start] + bytes(builder.end()) + data[-8:])
    with LogFile(liar) as log, pytest.raises(DamagedLog, match="outside the times its index"):
        list(log.messages())
