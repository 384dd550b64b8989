"""Where reading a damaged MCAP file may resume (:func:`service.logs.logtools.recover`).

After an unreadable record (a corrupted length, garbage), the next record worth reading is a
chunk whose CRC over its decompressed records checks out, or a metadata record with a sensible
name: found by trying each byte that is such a record's opcode, so a damaged stretch costs only
itself.
"""

from __future__ import annotations

import re
from typing import IO

from mcap.records import Chunk, Metadata
from mcap.stream_reader import StreamReader

from service.logs.mcapchunks import unpack_chunk

#: Opcodes of the records reading may resume at after an unreadable stretch.
_CHUNK, _METADATA = 0x06, 0x0C
_SCAN_BLOCK = 1 << 20
_METADATA_NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def _resumable(src: IO[bytes], at: int, size: int) -> bool:
    """Whether a chunk that checks out, or a metadata record, starts at ``at``."""
    src.seek(at)
    head = src.read(9)
    if len(head) < 9:
        return False
    opcode, length = head[0], int.from_bytes(head[1:], "little")
    if opcode not in (_CHUNK, _METADATA) or at + 9 + length > size or length < 8:
        return False
    src.seek(at)
    try:
        record = next(iter(StreamReader(src, skip_magic=True, emit_chunks=True).records))
        if isinstance(record, Chunk):
            unpack_chunk(record)
            return record.uncompressed_crc != 0  # a CRC was written: it is what checked out
        return isinstance(record, Metadata) and _METADATA_NAME.fullmatch(record.name) is not None
    except Exception:
        return False


def next_readable(src: IO[bytes], start: int, size: int) -> int | None:
    """The offset of the next record at or after ``start`` that reading may resume at."""
    pos = start
    while pos < size:
        src.seek(pos)
        block = src.read(_SCAN_BLOCK)
        for i, byte in enumerate(block):
            if byte in (_CHUNK, _METADATA) and _resumable(src, pos + i, size):
                return pos + i
        pos += len(block)
    return None
