"""rmw_zenoh's sample attachment: sequence number, source timestamp and publisher GID.

rmw_zenoh writes it with zenoh-ext's ``Serializer`` (``attachment_helpers.cpp``, the same on
Humble, Jazzy, Kilted and Rolling): int64 sequence number (from 1, per publisher), int64 source
timestamp (ns since the epoch), then a 16-byte array, which the serializer prefixes with its
LEB128 length (one byte, 16). 33 bytes in all. A ROS subscriber drops a sample without it.
"""

from __future__ import annotations

import hashlib
import struct
import threading
from typing import NamedTuple

GID_SIZE = 16
SIZE = 8 + 8 + 1 + GID_SIZE
_HEAD = struct.Struct("<qqB")


class Attachment(NamedTuple):
    """A decoded attachment."""

    sequence: int
    source_ns: int
    gid: bytes


def pack(sequence: int, source_ns: int, gid: bytes) -> bytes:
    """The 33 bytes of an attachment."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(gid)}")
    return _HEAD.pack(sequence, source_ns, GID_SIZE) + gid


def unpack(data: bytes) -> Attachment | None:
    """Decode an attachment; ``None`` when it is not one of rmw_zenoh's."""
    if len(data) != SIZE:
        return None
    sequence, source_ns, length = _HEAD.unpack_from(data)
    if length != GID_SIZE:
        return None
    return Attachment(sequence, source_ns, bytes(data[_HEAD.size :]))


def gid_of(token_key: str) -> bytes:
    """A GID stable per publisher: a 128-bit hash of its liveliness token.

    rmw_zenoh uses XXH3-128 of the same string; subscribers only need the GID to be stable and
    unique per publisher, so the standard library's BLAKE2b stands in for it.
    """
    return hashlib.blake2b(token_key.encode(), digest_size=GID_SIZE).digest()


class Sequencer:
    """The attachments of one publisher: its GID and a sequence number from 1."""

    def __init__(self, gid: bytes) -> None:
        self.gid = gid
        self._next = 1
        self._lock = threading.Lock()

    def next(self, source_ns: int) -> bytes:
        """The attachment of the next sample, stamped ``source_ns``."""
        with self._lock:
            seq = self._next
            self._next += 1
        return pack(seq, source_ns, self.gid)
