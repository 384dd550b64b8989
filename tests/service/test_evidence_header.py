"""A map evidence header is bounded before it is parsed.

Found by a reviewer attacking a running ``rlutf serve``: any client may put on
``{prefix}/service/{x}/mapevidence``, and the header line is JSON inside a zstd frame of up to
``max_map_bytes`` (64 MiB) decompressed. 5.5 kB put there decompressed to a 60 MB header of
20,000,000 empty objects: ``json.loads`` built them in 1.7 s, holding the interpreter's lock
(every thread of the service stood still), and 1.5 GB. Real payloads, no mocks.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zstandard

from rlutf.mapchange import GridCounts
from service.evidence import MAX_MAPS, MAX_ROBOTS, decode_evidence, encode_evidence
from service.maphealth import Handed


def _bomb(items: bytes, n: int) -> bytes:
    raw = b'{"maps":[],"x":[' + items * n + b"0]}\n"
    return bytes(zstandard.ZstdCompressor(level=3).compress(raw))


@pytest.mark.parametrize("items", [b"{},", b"[],", b"0,", b'"a",'])
def test_a_header_of_millions_of_items_is_refused_unparsed(items: bytes) -> None:
    payload = _bomb(items, 2_000_000)
    assert len(payload) < 10_000
    start = time.process_time()
    with pytest.raises(ValueError, match=r"not parsed|too many lists"):
        decode_evidence(payload, 64 << 20)
    assert time.process_time() - start < 0.5


def test_the_largest_real_headers_are_still_read() -> None:
    """100,000 robot ids of 64 characters on one map version; 64 map versions."""
    ids = frozenset(f"{i:06d}".ljust(64, "r") for i in range(MAX_ROBOTS))
    empty = np.zeros((7, 0), np.int32), np.zeros((4, 0), np.int64)
    one = GridCounts((10, 8), np.zeros(0, np.int64), *empty, 1, 1, 2, ids)
    (got,) = decode_evidence(encode_evidence([Handed("m1", 1, one)]), 64 << 20)
    assert got.counts.robot_ids == ids
    few = GridCounts((10, 8), np.zeros(0, np.int64), *empty, 1, 1, 2, frozenset({"a", "b"}))
    many = [Handed(f"m{i}", 1, few) for i in range(MAX_MAPS)]
    assert len(decode_evidence(encode_evidence(many), 64 << 20)) == MAX_MAPS
