"""A chunked, zstd-compressed MCAP writer that costs little per message.

The recorder writes every input and pose of the fleet, thousands of messages a second, on a
thread of the service's main process, whose interpreter lock the Zenoh callbacks wait for.
``mcap.writer.Writer`` builds a dataclass per message and writes its fields one ``struct.pack``
and one ``BytesIO.write`` at a time, about 8 us a message; :class:`McapWriter` packs a message's
header in one call and appends it with its payload to the open chunk, and reuses one zstd
compressor. Its files are byte for byte those of ``mcap.writer.Writer`` (default options:
chunked, zstd, every index, summary and statistics, no data CRC) given the same calls and the
same zstd level (mcap's is 3); ``tests/service/logs/test_mcapwriter.py`` compares the two.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping
from typing import IO

import zstandard

MAGIC = b"\x89MCAP0\r\n"
LIBRARY = "rlutf"
ZSTD = "zstd"
#: The zstd level of mcap's own writer.
MCAP_ZSTD_LEVEL = 3

_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_MESSAGE_INDEX, _CHUNK_INDEX, _ATTACHMENT_INDEX, _STATISTICS = 0x07, 0x08, 0x0A, 0x0B
_METADATA, _METADATA_INDEX, _SUMMARY_OFFSET, _DATA_END = 0x0C, 0x0D, 0x0E, 0x0F

_OPCODE = struct.Struct("<BQ")
#: A Message record's header: opcode, record length, channel, sequence, log and publish time.
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIELDS = 2 + 4 + 8 + 8


def _record(opcode: int, body: bytes) -> bytes:
    return _OPCODE.pack(opcode, len(body)) + body


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _map(items: Mapping[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in items.items())
    return struct.pack("<I", len(body)) + body


class McapWriter:
    """Writes one MCAP file to a binary stream (see the module docstring).

    Not thread-safe: one thread owns it.

    Args:
        stream: where the file goes; the caller closes it after :meth:`finish`.
        chunk_size: a chunk is closed once its uncompressed records pass this many bytes.
        zstd_level: the chunks' zstd compression level.
    """

    def __init__(
        self, stream: IO[bytes], chunk_size: int = 1024 * 1024, zstd_level: int = MCAP_ZSTD_LEVEL
    ) -> None:
        self._stream = stream
        self._chunk_size = chunk_size
        self._compress = zstandard.ZstdCompressor(level=zstd_level).compress
        self._chunk = bytearray()
        self._chunk_messages = 0
        self._chunk_start = 0
        self._chunk_end = 0
        self._index: dict[int, list[int]] = {}  # channel: log time, offset, log time, ...
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self.counts: dict[int, int] = {}
        """Messages written per channel id (the next message's sequence number)."""
        self._messages = 0
        self._start = 0
        self._end = 0
        self._chunks = 0
        self._metadata = 0
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []

    def start(self, profile: str = "", library: str = LIBRARY) -> None:
        """Write the magic and the header."""
        self._stream.write(MAGIC + _record(_HEADER, _string(profile) + _string(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Add a schema (into the open chunk); its id."""
        schema_id = len(self._schemas) + 1
        body = struct.pack("<H", schema_id) + _string(name) + _string(encoding)
        record = _record(_SCHEMA, body + struct.pack("<I", len(data)) + data)
        self._schemas.append(record)
        self._chunk += record
        self._maybe_close_chunk()
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        """Add a channel without metadata (into the open chunk); its id."""
        channel_id = len(self._channels) + 1
        body = struct.pack("<HH", channel_id, schema_id) + _string(topic)
        record = _record(_CHANNEL, body + _string(message_encoding) + _map({}))
        self._channels.append(record)
        self._chunk += record
        self._maybe_close_chunk()
        return channel_id

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        """Add a message to the open chunk; its sequence number counts the channel's messages
        in this file (from 0, modulo 2**32)."""
        counts = self.counts
        sequence = counts.get(channel_id, 0)
        counts[channel_id] = sequence + 1
        if self._messages == 0:
            self._start = self._end = log_time
        elif log_time < self._start:
            self._start = log_time
        elif log_time > self._end:
            self._end = log_time
        self._messages += 1
        if self._chunk_messages == 0:
            self._chunk_start = self._chunk_end = log_time
        elif log_time < self._chunk_start:
            self._chunk_start = log_time
        elif log_time > self._chunk_end:
            self._chunk_end = log_time
        self._chunk_messages += 1
        chunk = self._chunk
        index = self._index.get(channel_id)
        if index is None:
            index = self._index[channel_id] = []
        index += (log_time, len(chunk))
        chunk += _MESSAGE_HEAD.pack(
            _MESSAGE,
            _MESSAGE_FIELDS + len(data),
            channel_id,
            sequence & 0xFFFFFFFF,
            log_time,
            publish_time,
        )
        chunk += data
        if len(chunk) > self._chunk_size:
            self._close_chunk()

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write a metadata record (now, before the open chunk)."""
        offset = self._stream.tell()
        record = _record(_METADATA, _string(name) + _map(data))
        self._stream.write(record)
        self._metadata += 1
        self._metadata_indexes.append(
            _record(_METADATA_INDEX, struct.pack("<QQ", offset, len(record)) + _string(name))
        )

    def flush(self) -> None:
        """Close the open chunk (if it holds a message) and flush the stream."""
        self._close_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """Close the open chunk; write the data end, the summary and the footer."""
        self._close_chunk()
        stream = self._stream
        stream.write(_record(_DATA_END, struct.pack("<I", 0)))
        summary_start = stream.tell()
        statistics = struct.pack(
            "<QHIIIIQQ",
            self._messages,
            len(self._schemas),
            len(self._channels),
            0,
            self._metadata,
            self._chunks,
            self._start,
            self._end,
        )
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in self.counts.items())
        groups = [
            (_SCHEMA, b"".join(self._schemas)),
            (_CHANNEL, b"".join(self._channels)),
            (_STATISTICS, _record(_STATISTICS, statistics + _map_length(counts) + counts)),
            (_CHUNK_INDEX, b"".join(self._chunk_indexes)),
            (_ATTACHMENT_INDEX, b""),
            (_METADATA_INDEX, b"".join(self._metadata_indexes)),
        ]
        summary = bytearray()
        offsets = bytearray()
        for opcode, group in groups:
            offsets += _record(
                _SUMMARY_OFFSET,
                struct.pack("<BQQ", opcode, summary_start + len(summary), len(group)),
            )
            summary += group
        offsets_start = summary_start + len(summary)
        summary += offsets
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", _FOOTER, 20, summary_start, offsets_start), crc)
        stream.write(summary)
        stream.write(_record(_FOOTER, struct.pack("<QQI", summary_start, offsets_start, crc)))
        stream.write(MAGIC)

    def _maybe_close_chunk(self) -> None:
        if len(self._chunk) > self._chunk_size:
            self._close_chunk()

    def _close_chunk(self) -> None:
        if self._chunk_messages == 0:
            return  # schemas and channels stay in the open chunk
        self._chunks += 1
        data = self._chunk  # not copied: compressed and summed in place
        compressed = self._compress(data)
        stream = self._stream
        start = stream.tell()
        head = struct.pack(
            "<QQQI", self._chunk_start, self._chunk_end, len(data), zlib.crc32(data)
        ) + _string(ZSTD)
        head += struct.pack("<Q", len(compressed))
        stream.write(_OPCODE.pack(_CHUNK, len(head) + len(compressed)) + head)
        stream.write(compressed)  # not copied into the record either
        chunk_length = _OPCODE.size + len(head) + len(compressed)
        indexes = bytearray()
        offsets = bytearray()
        position = start + chunk_length
        for channel_id, entries in self._index.items():
            offsets += struct.pack("<HQ", channel_id, position + len(indexes))
            pairs = struct.pack(f"<{len(entries)}Q", *entries)
            indexes += _record(_MESSAGE_INDEX, struct.pack("<HI", channel_id, len(pairs)) + pairs)
        stream.write(indexes)
        self._chunk_indexes.append(
            _record(
                _CHUNK_INDEX,
                struct.pack("<QQQQ", self._chunk_start, self._chunk_end, start, chunk_length)
                + _map_length(offsets)
                + offsets
                + struct.pack("<Q", len(indexes))
                + _string(ZSTD)
                + struct.pack("<QQ", len(compressed), len(data)),
            )
        )
        self._chunk.clear()
        self._index.clear()
        self._chunk_messages = 0


def _map_length(entries: bytes | bytearray) -> bytes:
    return struct.pack("<I", len(entries))
