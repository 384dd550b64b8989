"""McapWriter writes the bytes mcap's own Writer writes, given the same calls, and LogWriter the
bytes it wrote when it was built on mcap's Writer (at mcap's zstd level)."""

from __future__ import annotations

import io
import random
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from mcaplog_fixtures import simulated_inputs

from service.logs.mcapfile import (
    CONFIG_METADATA,
    LIBRARY,
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    LogWriter,
    Record,
    config_metadata,
    schema_data,
)
from service.logs.mcapwriter import MCAP_ZSTD_LEVEL, McapWriter

Calls = list[tuple[str, tuple[Any, ...]]]


def _calls(seed: int) -> Calls:
    """A random session: schemas, channels, messages (times out of order too), metadata,
    flushes, in the order a recorder makes them."""
    rng = random.Random(seed)
    calls: Calls = [("start", ("", "rlutf test"))]
    schemas = channels = 0
    t = 1_700_000_000_000_000_000
    for _ in range(rng.randint(50, 400)):
        roll = rng.random()
        if schemas == 0 or roll < 0.02:
            schemas += 1
            calls.append(("schema", (f"rlutf.S{schemas}", "jsonschema", rng.randbytes(40))))
        elif channels == 0 or roll < 0.06:
            channels += 1
            calls.append(
                ("channel", (f"rlutf/robots/r{channels}/scan", "json", rng.randint(0, schemas)))
            )
        elif roll < 0.08:
            calls.append(
                ("metadata", (f"m{rng.randint(0, 3)}", {"json": "{}" * rng.randint(0, 9)}))
            )
        elif roll < 0.1:
            calls.append(("flush", ()))
        else:
            t += rng.randint(-2_000_000, 5_000_000)  # now and then earlier than the last
            size = rng.choice((20, 300, 3000, 9000))
            data = bytes(rng.choice(b"0123456789., ") for _ in range(size))
            calls.append(("message", (rng.randint(1, channels), t, data, t - 1000)))
    return calls


_METHODS = {"schema": "register_schema", "channel": "register_channel", "metadata": "add_metadata"}


def _play(writer: Writer | McapWriter, calls: Calls) -> None:
    """Make the calls on ``writer``; a message to mcap's Writer gets the sequence number
    McapWriter gives it (the channel's messages so far)."""
    sequence: dict[int, int] = {}
    for name, args in calls:
        if name != "message":
            getattr(writer, _METHODS.get(name, name))(*args)
        elif isinstance(writer, McapWriter):
            writer.add_message(*args)
        else:
            n = sequence[args[0]] = sequence.get(args[0], -1) + 1
            writer.add_message(*args, n)
    writer.finish()


def _theirs(calls: Calls, chunk_size: int) -> bytes:
    out = io.BytesIO()
    _play(Writer(out, chunk_size=chunk_size, compression=CompressionType.ZSTD), calls)
    return out.getvalue()


def _ours(calls: Calls, chunk_size: int, level: int = MCAP_ZSTD_LEVEL) -> bytes:
    out = io.BytesIO()
    _play(McapWriter(out, chunk_size, level), calls)
    return out.getvalue()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("chunk_size", [1, 4096, 64 * 1024, 1024 * 1024])
def test_same_bytes_as_mcap_writer(seed: int, chunk_size: int) -> None:
    calls = _calls(seed)
    ours = _ours(calls, chunk_size)
    assert ours == _theirs(calls, chunk_size)
    _reads_back(ours, calls)  # and mcap's reader reads it, messages in order, summary and all


def _reads_back(data: bytes, calls: Calls) -> None:
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    sent = [a for n, a in calls if n == "message"]
    assert summary.statistics.message_count == len(sent)
    in_file_order = reader.iter_messages(log_time_order=False)
    got = [(m.channel_id, m.log_time, m.data) for _, _, m in in_file_order]
    assert got == [(c, t, d) for c, t, d, _ in sent]


def test_empty_file_same_bytes() -> None:
    calls: Calls = [("start", ("", "x"))]
    assert _ours(calls, 1024) == _theirs(calls, 1024)


def test_zstd_level_changes_only_the_chunks() -> None:
    calls = _calls(3)
    ours, theirs = _ours(calls, 64 * 1024, level=1), _theirs(calls, 64 * 1024)
    assert ours != theirs and len(ours) < len(theirs) * 1.2
    _reads_back(ours, calls)


class _OldLogWriter:
    """``service.logs.mcapfile.LogWriter`` as it was on ``mcap.writer.Writer`` (``c85df9d``)."""

    def __init__(self, output: io.BytesIO, chunk_size: int) -> None:
        self._writer = Writer(output, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}

    def write(self, record: Record) -> None:
        key = (record.topic, record.schema_name)
        channel = self._channels.get(key)
        if channel is None:
            schema_id = self._schemas.get(record.schema_name)
            if schema_id is None:
                data = schema_data(record.schema_name)
                schema_id = 0
                if data is not None:
                    schema_id = self._writer.register_schema(
                        record.schema_name, SCHEMA_ENCODING, data
                    )
                self._schemas[record.schema_name] = schema_id
            channel = self._writer.register_channel(record.topic, MESSAGE_ENCODING, schema_id)
            self._channels[key] = channel
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        self._writer.add_message(
            channel_id=channel,
            log_time=record.log_time_ns,
            data=record.payload,
            publish_time=record.publish_time_ns,
            sequence=sequence % 2**32,
        )


@pytest.mark.parametrize("chunk_size", [2048, 1024 * 1024])
def test_log_writer_writes_the_bytes_it_wrote_on_mcaps_writer(chunk_size: int) -> None:
    records = simulated_inputs(steps=6)
    old_out, new_out = io.BytesIO(), io.BytesIO()
    old = _OldLogWriter(old_out, chunk_size)
    new = LogWriter(new_out, None, chunk_size, zstd_level=MCAP_ZSTD_LEVEL)
    config = {"prefix": "rlutf", "workers": 0}
    old._writer.add_metadata(CONFIG_METADATA, config_metadata(config))
    new.write_config(config)
    for i, r in enumerate(records):
        old.write(r)
        new.write(r)
        if i % 50 == 49:
            old._writer.flush()
            new.flush()
    old._writer.finish()
    new.finish()
    assert new_out.getvalue() == old_out.getvalue()
    assert new.messages == len(records)
