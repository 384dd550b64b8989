"""Map health evidence on the bus (:mod:`service.evidence`): what one instance counted reaches
the others exactly, and a payload that is not such evidence is refused with why, before any of
it is merged."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zstandard

from rlutf.mapchange import GridCounts
from service.evidence import CELL_BYTES, decode_evidence, encode_evidence
from service.maphealth import Handed


def _handed(map_id: str = "m1", cells: tuple[int, ...] = (3, 7, 40)) -> Handed:
    k = len(cells)
    rng = np.random.default_rng(len(map_id))
    counts = rng.integers(0, 50, (7, k)).astype(np.int32)
    times = rng.integers(10**18, 2 * 10**18, (4, k)).astype(np.int64)
    grid = GridCounts(
        (10, 8), np.array(cells, dtype=np.int64), counts, times, 12, 10**18, 2 * 10**18,
        frozenset({"r1", "r2"}),
    )  # fmt: skip
    return Handed(map_id, 2, grid)


def test_evidence_round_trips_exactly() -> None:
    handed = [_handed(), _handed("floor-2", (0, 79)), _handed("empty", ())]
    (a, b, c) = decode_evidence(encode_evidence(handed))
    for got, want in zip((a, b, c), handed, strict=True):
        assert (got.map_id, got.version) == (want.map_id, want.version)
        g, w = got.counts, want.counts
        assert g.shape == w.shape and (g.scans, g.oldest_ns, g.newest_ns) == (
            w.scans,
            w.oldest_ns,
            w.newest_ns,
        )
        assert g.robot_ids == w.robot_ids
        for x, y in ((g.cells, w.cells), (g.counts, w.counts), (g.times, w.times)):
            assert x.dtype == y.dtype and np.array_equal(x, y)


def _raw(payload: bytes) -> bytes:
    return bytes(zstandard.ZstdDecompressor().decompress(payload))


def _zst(raw: bytes) -> bytes:
    return bytes(zstandard.ZstdCompressor().compress(raw))


def _stream(raw: bytes) -> bytes:
    """A frame that does not say its size (written as a stream)."""
    return bytes(zstandard.ZstdCompressor(write_content_size=False).compress(raw))


def _with(change: dict[str, object]) -> bytes:
    head, _, body = _raw(encode_evidence([_handed()])).partition(b"\n")
    doc = json.loads(head)
    doc["maps"][0].update(change)
    return _zst(json.dumps(doc).encode() + b"\n" + body)


@pytest.mark.parametrize(
    ("payload", "said"),
    [
        (b"", "not a zstd frame"),
        (b"plain text", "not a zstd frame"),
        (_zst(bytes(2_000_000)), "not a zstd frame of at most 1000000 bytes"),  # a bomb
        (_stream(bytes(2_000_000)), "not a zstd frame of at most 1000000 bytes"),  # unsized
        (_zst(b""), "no header"),
        (_zst(b"{not json\n"), "not JSON"),
        (_zst(b"[" * 100_000 + b"]" * 100_000 + b"\n"), "not JSON"),  # past the parser's depth
        (_zst(b'{"maps": 3}\n'), "'maps' must be a list"),
        (_zst(b'{"maps": [' + b"{}," * 70 + b"{}]}\n"), "'maps' must be a list of at most"),
        (_zst(_raw(encode_evidence([_handed()]))[:-5]), "shorter than its header"),
        (_zst(_raw(encode_evidence([_handed()])) + b"x"), "longer than its header"),
        (_with({"map_id": "../etc"}), "'map_id' is not a map id"),
        (_with({"version": -1}), "'version' must be a whole number"),
        (_with({"shape": [10]}), "'shape' must be"),
        (_with({"shape": [10**5, 10**5]}), "more than"),
        (_with({"cells": 82, "shape": [9, 9]}), "more cells than the grid"),
        (_with({"shape": [5, 4]}), "a cell index outside the grid"),
        (_with({"robots": ["bad id"]}), "'robots' must be a list of robot ids"),
        (_with({"scans": 1.5}), "'scans' must be a whole number"),
    ],
)
def test_a_payload_that_is_not_evidence_is_refused_with_why(payload: bytes, said: str) -> None:
    with pytest.raises(ValueError, match=said):
        decode_evidence(payload, 1_000_000)


def test_repeated_cells_and_negative_counts_are_refused() -> None:
    payload = encode_evidence([_handed(cells=(3, 3, 40))])
    with pytest.raises(ValueError, match="a cell given twice"):
        decode_evidence(payload)
    for row, value, said in ((1, -4, "a count below 0"), (2, 10**9, "above 100000000")):
        bad = _handed()
        bad.counts.counts[row, 0] = value
        with pytest.raises(ValueError, match=said):
            decode_evidence(encode_evidence([bad]))
    bad = _handed()
    bad.counts.times[3, 1] = -1  # a stamp the MapHealth it would make could not carry
    with pytest.raises(ValueError, match="a stamp below 0"):
        decode_evidence(encode_evidence([bad]))
    assert len(_raw(encode_evidence([_handed()])).partition(b"\n")[2]) == 3 * CELL_BYTES
