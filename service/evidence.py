"""Map health evidence between service instances: one instance's counts, on the bus.

Each instance (each process of ``rlutf serve``, each instance of a fleet deployment) counts the
map health evidence of its own robots' scans (:mod:`service.maphealth`). A MapHealth of only a
share of the fleet would miss what the other robots see and, with every instance putting its
own on ``{prefix}/maphealth/{map_id}``, a subscriber would read reports of different fleets in
turn. So every instance also puts the evidence it hands on (at most once a second) on
``{prefix}/service/{instance}/mapevidence``, and merges what the others put: the grids are
sums, ORs, minima and maxima (:meth:`rlutf.mapchange.ChangeGrid.merge`), so every instance
holds the same grid once it has merged the same counts, whatever their order, and one instance
reports each map (``docs/extensions.md``).

The payload is a zstd frame (level 1; what it weighs: ``python -m bench.evidence``,
BENCHMARKS.md "Map health evidence between instances") of one line
of JSON (per map version counted: ``map_id``, ``version``, ``shape`` ``[nx, ny]``, ``cells``
(K), ``scans``, ``oldest_ns``, ``newest_ns``, ``robots``), a newline, then per map version its
arrays, little-endian: the K flat cell indices (int64), the ``7 x K`` counts (int32) and the
``4 x K`` stamps (int64). :func:`decode_evidence` decompresses at most the size it is given and
checks every size and index before anything is merged: a payload from any client costs bounded
time and memory.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

import numpy as np
import zstandard

from rlutf.mapchange import GridCounts
from schemas import valid_id
from service.maphealth import Handed

#: Cells of one grid at most (a 1 km x 1 km map at the default 0.1 m cells is 10^8: far more
#: than any building here; the receiving grid's own size is checked too).
MAX_CELLS = 100_000_000
#: A cell's count in one payload at most (a second of 100 robots' scans puts thousands, not
#: millions, in the busiest cell; the grid's sums are int32, so one payload cannot wrap them).
MAX_COUNT = 100_000_000
#: Map versions in one payload at most.
MAX_MAPS = 64
#: Robot ids named in one map version's counts at most.
MAX_ROBOTS = 100_000
#: Bytes of the header line at most: 100,000 robot ids of 64 characters, quoted, and the rest.
HEADER_MAX = 8 << 20
#: Items of the header's lists and objects at most (its commas): the robot ids of every map
#: version and a few fields each. A zstd frame of 5.5 kB decompressed to a 60 MB header of
#: 20,000,000 empty objects, which ``json.loads`` built in 1.7 s holding the interpreter's lock
#: (every thread of the service stood still) and 1.5 GB; now refused before it is parsed.
HEADER_ITEMS = MAX_ROBOTS + 16 * MAX_MAPS
_CELL = np.dtype("<i8")
_COUNT = np.dtype("<i4")
_TIME = np.dtype("<i8")
#: Bytes per touched cell: its index, 7 counts, 4 stamps.
CELL_BYTES = _CELL.itemsize + 7 * _COUNT.itemsize + 4 * _TIME.itemsize


def encode_evidence(handed: Iterable[Handed]) -> bytes:
    """The payload of evidence handed on (see the module docstring)."""
    heads: list[dict[str, Any]] = []
    blocks: list[bytes] = []
    for h in handed:
        c = h.counts
        heads.append(
            {
                "map_id": h.map_id,
                "version": h.version,
                "shape": list(c.shape),
                "cells": len(c.cells),
                "scans": c.scans,
                "oldest_ns": c.oldest_ns,
                "newest_ns": c.newest_ns,
                "robots": sorted(c.robot_ids),
            }
        )
        blocks += [
            np.ascontiguousarray(c.cells, dtype=_CELL).tobytes(),
            np.ascontiguousarray(c.counts, dtype=_COUNT).tobytes(),
            np.ascontiguousarray(c.times, dtype=_TIME).tobytes(),
        ]
    raw = json.dumps({"maps": heads}, separators=(",", ":")).encode() + b"\n" + b"".join(blocks)
    return bytes(zstandard.ZstdCompressor(level=1).compress(raw))


def decode_evidence(payload: bytes, max_bytes: int = 64 << 20) -> list[Handed]:
    """The evidence of a payload :func:`encode_evidence` wrote, of at most ``max_bytes``
    uncompressed.

    Raises:
        ValueError: anything else (the message says what).
    """
    try:
        # the size a frame declares is what decompress() allocates: checked first (a frame
        # that declares none is decompressed into at most max_bytes)
        if zstandard.frame_content_size(payload) > max_bytes:
            raise zstandard.ZstdError(f"it declares {zstandard.frame_content_size(payload)}")
        raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=max_bytes)
    except zstandard.ZstdError as err:
        raise ValueError(
            f"map evidence: not a zstd frame of at most {max_bytes} bytes ({err})"
        ) from None
    head, sep, body = raw.partition(b"\n")
    if not sep:
        raise ValueError("map evidence: no header line")
    if len(head) > HEADER_MAX or head.count(b",") > HEADER_ITEMS:
        raise ValueError(
            f"map evidence: header of {len(head)} bytes or {head.count(b',') + 1} items, more "
            f"than {HEADER_MAX} or {HEADER_ITEMS}: not parsed"
        )
    if head.count(b"{") > MAX_MAPS + 1:
        raise ValueError(f"map evidence: 'maps' must be a list of at most {MAX_MAPS} (not parsed)")
    if head.count(b"[") > 2 * MAX_MAPS + 1:  # each map version has two lists
        raise ValueError("map evidence: header is not JSON of map evidence: too many lists")
    try:
        doc = json.loads(head)
    except (ValueError, RecursionError) as err:  # nested past the parser's depth: not a header
        raise ValueError(f"map evidence: header is not JSON ({err})") from None
    maps = doc.get("maps") if isinstance(doc, dict) else None
    if not isinstance(maps, list) or len(maps) > MAX_MAPS:
        raise ValueError(f"map evidence: 'maps' must be a list of at most {MAX_MAPS}")
    out: list[Handed] = []
    at = 0
    for m in maps:
        map_id, version, shape, k, robots = _fields(m)
        size = k * CELL_BYTES
        if at + size > len(body):
            raise ValueError("map evidence: shorter than its header says")
        cells = np.frombuffer(body, _CELL, k, at).astype(np.int64)
        at += k * _CELL.itemsize
        counts = np.frombuffer(body, _COUNT, 7 * k, at).reshape(7, k).astype(np.int32)
        at += 7 * k * _COUNT.itemsize
        times = np.frombuffer(body, _TIME, 4 * k, at).reshape(4, k).astype(np.int64)
        at += 4 * k * _TIME.itemsize
        if k and (cells.min() < 0 or cells.max() >= shape[0] * shape[1]):
            raise ValueError("map evidence: a cell index outside the grid")
        if k and len(np.unique(cells)) != k:
            raise ValueError("map evidence: a cell given twice")
        if (counts[:3] < 0).any() or (counts[:3] > MAX_COUNT).any():
            raise ValueError(f"map evidence: a count below 0 or above {MAX_COUNT}")
        if (times < 0).any():
            raise ValueError("map evidence: a stamp below 0")
        counts_of = GridCounts(
            shape,
            cells,
            counts,
            times,
            _whole(m.get("scans"), "scans"),
            _whole(m.get("oldest_ns"), "oldest_ns"),
            _whole(m.get("newest_ns"), "newest_ns"),
            frozenset(robots),
        )
        out.append(Handed(map_id, version, counts_of))
    if at != len(body):
        raise ValueError("map evidence: longer than its header says")
    return out


def _fields(m: Any) -> tuple[str, int, tuple[int, int], int, list[str]]:
    if not isinstance(m, dict):
        raise ValueError("map evidence: each map must be an object")
    map_id = m.get("map_id")
    if not isinstance(map_id, str) or not valid_id(map_id):
        raise ValueError("map evidence: 'map_id' is not a map id")
    version = _whole(m.get("version"), "version")
    shape = m.get("shape")
    if not (isinstance(shape, list) and len(shape) == 2):
        raise ValueError("map evidence: 'shape' must be [nx, ny]")
    nx, ny = (_whole(v, "shape") for v in shape)
    if nx * ny > MAX_CELLS:
        raise ValueError(f"map evidence: a grid of more than {MAX_CELLS} cells")
    k = _whole(m.get("cells"), "cells")
    if k > nx * ny:
        raise ValueError("map evidence: more cells than the grid holds")
    robots = m.get("robots")
    if not (
        isinstance(robots, list)
        and len(robots) <= MAX_ROBOTS
        and all(isinstance(r, str) and valid_id(r) for r in robots)
    ):
        raise ValueError("map evidence: 'robots' must be a list of robot ids")
    return map_id, version, (nx, ny), k, robots


def _whole(value: Any, name: str) -> int:
    if type(value) is not int or value < 0:
        raise ValueError(f"map evidence: {name!r} must be a whole number >= 0")
    return value
