"""Occupancy grids from laser scans with known poses, and the CARMEN log reader.

Every beam with a return marks the cell of its end point as hit and every other cell it
crosses on the way as passed (an exact grid traversal, each cell once per beam). A cell's
occupancy is its hit ratio ``hits / (hits + passes)``; cells seen fewer than
``min_observations`` times are unknown, and the rest are classified with the map_server
thresholds (occupied above ``occupied_thresh``, free below ``free_thresh``, unknown between).
Beams without a return (range not finite, at most ``range_min``, or at least the scan's max
range) mark nothing: a missing echo says little about where the free space ends.

CARMEN logs (``FLASER`` lines, see ``bench/data/README.md``): a scan of ``n`` beams starts
at -pi/2 and is spaced pi/n for even n and pi/(n - 1) for odd n; its ``x y theta`` is the
laser's pose. Other message types are skipped. Gzip-compressed logs are read transparently.
A range written ``nan``, ``inf`` or ``1e999`` (infinite) is read, as CARMEN's own reader
(``strtod``) reads it, and is no return, as ROS's REP 117 defines non-finite ranges; a pose that
is not finite is refused with its line. A last line cut short (the log of a crashed logger ends
mid-line) is left out and named in :attr:`CarmenLog.cut`; a malformed line anywhere else is
refused.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from service.infile import read_regular, too_large
from service.maps.mapimport.errors import (
    CarmenError,
    EmptyMapError,
    GridTooLargeError,
    MapFileError,
    MapImportError,
)
from service.maps.mapimport.grid import FloatArray, OccupancyGrid
from service.maps.mapimport.raymarch import traverse

#: Default sensor range (metres): CARMEN writes 81.83 or the sensor's maximum for no return.
DEFAULT_MAX_RANGE = 50.0
#: Cells the grid extends beyond the outermost pose or hit point.
_MARGIN_CELLS = 2
#: Traversal steps to collect before counting them (bounds memory).
_FLUSH_CELLS = 4_000_000
#: Bytes a grid cell takes while a map is built: two int64 counts, the count of a chunk, then
#: the classification's float64 temporaries (measured: 50 per cell at peak, the intel log at
#: 1 cm, 14 million cells, peaked at 840 MB with the polygons).
BUILD_BYTES_PER_CELL = 50
#: The cells :func:`build_grid` allows by default and ``rlutf map build`` always: about 800 MB
#: at :data:`BUILD_BYTES_PER_CELL`, at 5 cm a bounding box of 40,000 m2 (a 200 m square). ``rlutf
#: map build`` lets a grid take up to half the memory the host has available
#: (:func:`max_grid_cells`): a larger site builds where there is memory for it, and a typo
#: (``--resolution 0.0001`` on the intel log: 139 billion cells) is refused before anything is
#: allocated.
MAX_GRID_CELLS = 16_000_000


def max_grid_cells(available: int | None) -> int:
    """The most cells a map build allocates with ``available`` bytes of memory free (``rlutf map
    build`` gives ``service.cores.available_memory``: the system's, capped by a container's
    limit; ``None``: not known): as many as half of it holds, or :data:`MAX_GRID_CELLS`,
    whichever is more."""
    return max(MAX_GRID_CELLS, (available or 0) // 2 // BUILD_BYTES_PER_CELL)


class CarmenScan(NamedTuple):
    """One laser scan in the map frame, in the form :func:`build_grid` takes.

    Attributes:
        pose: ``(3,)`` laser pose ``(x, y, theta)``, metres and radians.
        ranges: ``(N,)`` ranges, metres.
        angles: ``(N,)`` beam angles relative to the laser's heading, radians.
        max_range: ranges at or above this are no return, metres.
    """

    pose: FloatArray
    ranges: FloatArray
    angles: FloatArray
    max_range: float


@dataclass(frozen=True, eq=False)
class CarmenLog:
    """The scans and odometry of a CARMEN log.

    Attributes:
        scans: the ``FLASER`` scans in file order.
        stamps: ``(S,)`` their timestamps, seconds.
        odometry: ``(M, 4)`` ``ODOM`` rows ``(timestamp, x, y, theta)``.
        cut: the last line, left out because it is incomplete (the log ends mid-line, as a
            crashed logger leaves it): its number and what it lacks; or that a gzip stream
            ends early; ``None`` if there is none.
    """

    scans: tuple[CarmenScan, ...]
    stamps: FloatArray
    odometry: FloatArray
    cut: str | None = None

    @property
    def poses(self) -> FloatArray:
        """``(S, 3)`` the scans' laser poses."""
        return np.array([s.pose for s in self.scans]).reshape(-1, 3)


def carmen_angles(n: int) -> FloatArray:
    """Beam angles of an ``n``-beam CARMEN scan: from -pi/2, pi/n apart (pi/(n-1) if n is odd)."""
    step = math.pi / n if n % 2 == 0 else math.pi / max(n - 1, 1)
    return -0.5 * math.pi + step * np.arange(n, dtype=np.float64)


def _floats(fields: Sequence[str], lineno: int) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError as err:
        raise CarmenError(f"line {lineno}: not a number in {' '.join(fields[:8])}...") from err


def parse_carmen(text: str | bytes, *, max_range: float = DEFAULT_MAX_RANGE) -> CarmenLog:
    """Parse a CARMEN log's text.

    Args:
        text: the log (already decompressed).
        max_range: the no-return range given to every scan, metres.

    Returns:
        The scans and odometry; an incomplete last line (no line end after it) that does not
        parse is left out and named in :attr:`CarmenLog.cut`.

    Raises:
        CarmenError: a malformed ``FLASER`` or ``ODOM`` line other than an incomplete last one
            (named by its number), or no scan.
    """
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    scans: list[CarmenScan] = []
    stamps: list[float] = []
    odometry: list[list[float]] = []
    angle_cache: dict[int, FloatArray] = {}
    lines = text.splitlines()
    unended = len(lines) if lines and not text.endswith(("\n", "\r")) else 0
    cut = None
    for lineno, line in enumerate(lines, start=1):
        try:
            _parse_line(line, lineno, scans, stamps, odometry, angle_cache, max_range)
        except CarmenError as err:
            if lineno != unended:
                raise
            cut = (
                f"{err}: the last line is cut short (the log ends mid-line, as a crashed logger "
                "leaves it) and is left out"
            )
    if not scans:
        raise CarmenError("the log holds no FLASER scan")
    return CarmenLog(
        tuple(scans),
        np.array(stamps),
        np.array(odometry, dtype=np.float64).reshape(-1, 4),
        cut,
    )


def _parse_line(
    line: str,
    lineno: int,
    scans: list[CarmenScan],
    stamps: list[float],
    odometry: list[list[float]],
    angle_cache: dict[int, FloatArray],
    max_range: float,
) -> None:
    """Add the scan or odometry of one line; other lines are skipped.

    Raises:
        CarmenError: a malformed ``FLASER`` or ``ODOM`` line, named by its number.
    """
    fields = line.split()
    if fields:
        if fields[0] == "FLASER":
            try:
                n = int(fields[1])
            except (IndexError, ValueError) as err:
                raise CarmenError(f"line {lineno}: FLASER needs a beam count") from err
            if n < 1 or len(fields) < n + 9:
                raise CarmenError(
                    f"line {lineno}: FLASER with {n} beams needs {n + 9} fields "
                    f"(n, ranges, x y theta, odom x y theta, timestamp), got {len(fields) - 1}"
                )
            values = _floats(fields[2 : n + 9], lineno)
            if n not in angle_cache:
                angle_cache[n] = carmen_angles(n)
            pose = np.array(values[n : n + 3])
            if not np.isfinite(pose).all():
                given = " ".join(fields[n + 2 : n + 5])
                raise CarmenError(f"line {lineno}: FLASER pose x y theta is not finite: {given}")
            scans.append(CarmenScan(pose, np.array(values[:n]), angle_cache[n], max_range))
            stamps.append(values[n + 6])
        elif fields[0] == "ODOM":
            if len(fields) < 8:
                raise CarmenError(f"line {lineno}: ODOM needs 7 fields, got {len(fields) - 1}")
            x, y, theta, _tv, _rv, _acc, stamp = _floats(fields[1:8], lineno)
            odometry.append([stamp, x, y, theta])


#: The most of a CARMEN log's text that is read (the public logs are tens of MB; every scan is
#: held in memory while the map is built).
MAX_CARMEN_BYTES = 1 << 30


def read_carmen(path: str | Path, *, max_range: float = DEFAULT_MAX_RANGE) -> CarmenLog:
    """Read a CARMEN log file, gzip-compressed or not.

    Raises:
        MapFileError: the file is missing, unreadable or a broken gzip stream.
        CarmenError: a malformed line.
    """
    p = Path(path)
    ended = True
    try:
        data = read_regular(p, MAX_CARMEN_BYTES)
        if data[:2] == b"\x1f\x8b":
            data, ended = _gunzip(data, MAX_CARMEN_BYTES)
            if len(data) > MAX_CARMEN_BYTES:
                raise too_large(p, MAX_CARMEN_BYTES)
    except (OSError, zlib.error) as err:
        why = err.strerror if isinstance(err, OSError) and err.strerror else err
        raise MapFileError(f"CARMEN log '{p}': cannot read: {why}") from err
    try:
        log = parse_carmen(data, max_range=max_range)
    except CarmenError as err:
        raise CarmenError(f"{p}: {err}") from err
    if not ended and log.cut is None:  # cut at a line's end: the lines read are whole
        log = replace(log, cut="the gzip stream ends early (a crashed logger's?): read to there")
    return log


def _gunzip(raw: bytes, max_bytes: int) -> tuple[bytes, bool]:
    """A gzip file's content, and whether its stream ended: a log compressed as it was written
    and cut by a crash is read to where it stops (``gzip.decompress`` refuses it whole), as a
    plain log cut mid-line is. Members after the first (``cat a.gz b.gz``) are read too. At most
    ``max_bytes`` and one more are inflated (a few MB of gzip can hold gigabytes of zeros): a
    result longer than ``max_bytes`` is the caller's to refuse.

    Raises:
        zlib.error: corrupt data (not a stream cut short).
    """
    out = []
    size = 0
    rest = raw
    while rest:
        stream = zlib.decompressobj(16 + zlib.MAX_WBITS)
        pending = rest
        while not stream.eof and size <= max_bytes:
            piece = stream.decompress(pending, max_bytes + 1 - size)
            out.append(piece)
            size += len(piece)
            pending = stream.unconsumed_tail
            if not piece and not pending:
                break  # the input is used up: a stream cut short
        if size > max_bytes or not stream.eof:
            return b"".join(out), stream.eof
        rest = stream.unused_data
    return b"".join(out), True


Scans = Iterable[tuple[ArrayLike, ArrayLike, ArrayLike, float]]
"""``(pose (3,), ranges (N,), angles (N,), max_range)`` per scan (:func:`build_grid`)."""

#: Beams whose cells are counted at once: a build takes the memory of this many beams (about
#: 300 bytes each), not of the whole log.
CHUNK_BEAMS = 250_000


def build_grid(
    scans: Scans | Callable[[], Scans],
    *,
    resolution: float = 0.05,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    min_observations: int = 1,
    range_min: float = 0.0,
    chunk_beams: int = CHUNK_BEAMS,
    max_cells: int = MAX_GRID_CELLS,
) -> OccupancyGrid:
    """Build an occupancy grid from scans taken at known poses.

    The scans are read twice, for the grid's extent and then for its cells, :data:`CHUNK_BEAMS`
    beams at a time, so a log of any length is built in the memory of a chunk (a mapping run of
    30 minutes at 40 Hz, 720 beams, is 52 million beams: 16 GB held at once). Counts add up,
    so the grid does not depend on ``chunk_beams``.

    Args:
        scans: ``(pose (3,), ranges (N,), angles (N,), max_range)`` per scan: the sensor's
            map-frame pose, ranges in metres (non-finite, ``<= range_min`` or
            ``>= max_range`` is no return) and beam angles relative to the sensor heading; or
            a function that gives them anew each call (a log read again rather than held: an
            iterator that can be read once is held in memory).
        resolution: cell size, metres.
        occupied_thresh: hit ratio above which a cell is occupied.
        free_thresh: hit ratio below which a cell is free.
        min_observations: cells seen (hit or passed) fewer times are unknown.
        range_min: ranges at or below this are no return, metres.
        chunk_beams: beams counted at once.
        max_cells: a larger grid is refused before it is allocated (``rlutf map build``:
            :func:`max_grid_cells`; :data:`BUILD_BYTES_PER_CELL` bytes a cell).

    Returns:
        The grid, axis-aligned (yaw 0), its origin on a multiple of the resolution, covering
        every pose and hit point with a margin of two cells.

    Raises:
        MapImportError: bad parameters, a scan of the wrong shape, or no beam with a return.
        GridTooLargeError: the grid would have more than ``max_cells`` cells (the message
            gives the cells, the memory and the resolution that would fit).
    """
    if not (math.isfinite(resolution) and resolution > 0):
        raise MapImportError(f"resolution: must be positive, got {resolution}")
    if not 0.0 <= free_thresh <= occupied_thresh <= 1.0:
        raise MapImportError(
            f"thresholds: need 0 <= free_thresh ({free_thresh}) <= occupied_thresh "
            f"({occupied_thresh}) <= 1"
        )
    if callable(scans):
        read = scans
    else:
        held = scans if isinstance(scans, Sequence) else list(scans)

        def read() -> Scans:
            return held

    low = np.full(2, np.inf)
    high = np.full(2, -np.inf)
    for start, end in _beams(read(), range_min):
        if len(end):
            low = np.minimum(low, np.minimum(start.min(axis=0), end.min(axis=0)))
            high = np.maximum(high, np.maximum(start.max(axis=0), end.max(axis=0)))
    if not np.isfinite(low).all():
        raise EmptyMapError("no beam with a return: nothing to build a map from")
    cols, rows, lo = _extent(low, high, resolution)
    size = rows * cols
    if size > max_cells:
        raise GridTooLargeError(_too_large(low, high, resolution, max_cells))
    hits = np.zeros(size, dtype=np.int64)
    passes = np.zeros(size, dtype=np.int64)
    for start, end in _chunks(_beams(read(), range_min), chunk_beams):
        o = start / resolution - lo
        e = end / resolution - lo
        length = np.hypot(*(e - o).T)
        direction = (e - o) / np.maximum(length, 1e-12)[:, None]
        hit_cell = np.floor(e).astype(np.int64)
        hit_flat = hit_cell[:, 1] * cols + hit_cell[:, 0]
        hits += np.bincount(hit_flat, minlength=size)
        pending: list[np.ndarray[tuple[int], np.dtype[np.int64]]] = []
        pending_count = 0
        for beam, flat, _ in traverse(o, direction, length, (rows, cols)):
            crossed = flat[flat != hit_flat[beam]]
            pending.append(crossed)
            pending_count += len(crossed)
            if pending_count > _FLUSH_CELLS:
                passes += np.bincount(np.concatenate(pending), minlength=size)
                pending, pending_count = [], 0
        if pending:
            passes += np.bincount(np.concatenate(pending), minlength=size)
    seen = hits + passes
    known = seen >= max(min_observations, 1)
    ratio = np.where(known, hits / np.maximum(seen, 1), np.nan)
    data = np.where(known, np.rint(100.0 * np.nan_to_num(ratio)), -1).astype(np.int8)
    return OccupancyGrid(
        data=data.reshape(rows, cols),
        free=(known & (np.nan_to_num(ratio, nan=1.0) < free_thresh)).reshape(rows, cols),
        occupied=(known & (np.nan_to_num(ratio) > occupied_thresh)).reshape(rows, cols),
        resolution=resolution,
        origin=(float(lo[0] * resolution), float(lo[1] * resolution), 0.0),
    )


def _extent(low: FloatArray, high: FloatArray, resolution: float) -> tuple[int, int, FloatArray]:
    """Columns, rows and lower-left cell of the grid that covers ``low`` to ``high`` (metres)
    with the margin."""
    lo = np.floor(low / resolution) - _MARGIN_CELLS
    hi = np.floor(high / resolution) + _MARGIN_CELLS
    return int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1, lo


def _too_large(low: FloatArray, high: FloatArray, resolution: float, max_cells: int) -> str:
    """Why a grid of the extent ``low`` to ``high`` is refused at ``resolution``, and the
    resolution (a whole number of millimetres) at which it would fit."""
    cols, rows, _ = _extent(low, high, resolution)
    size = cols * rows
    fits = math.ceil(resolution * math.sqrt(size / max_cells) * 1000.0) / 1000.0
    while math.prod(_extent(low, high, fits)[:2]) > max_cells:
        fits += 0.001
    width, height = high - low
    return (
        f"resolution {resolution:g} m: the grid would be {cols:,} x {rows:,} = {size:,} cells "
        f"(the scans span {width:.1f} x {height:.1f} m), about "
        f"{_bytes(size * BUILD_BYTES_PER_CELL)} to build; at most {max_cells:,} cells "
        f"({_bytes(max_cells * BUILD_BYTES_PER_CELL)}) are built here: give --resolution "
        f"{fits:g} or more"
    )


def _bytes(n: float) -> str:
    return f"{n / 1e9:,.1f} GB" if n >= 1e9 else f"{n / 1e6:,.0f} MB"


def _beams(scans: Scans, range_min: float) -> Iterator[tuple[FloatArray, FloatArray]]:
    """Per scan, the ``(B, 2)`` origins and ends of its beams with a return, map frame.

    Raises:
        MapImportError: a scan of the wrong shape (named by its number).
    """
    for k, (pose, ranges, angles, max_range) in enumerate(scans):
        p = np.asarray(pose, dtype=np.float64).reshape(-1)
        r = np.asarray(ranges, dtype=np.float64).reshape(-1)
        a = np.asarray(angles, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or r.shape != a.shape or not np.isfinite(p).all():
            raise MapImportError(
                f"scan {k}: need a finite pose (3,) and ranges and angles of one length, "
                f"got {p.shape}, {r.shape}, {a.shape}"
            )
        ok = np.isfinite(r) & (r > range_min) & (r < max_range)
        heading = p[2] + a[ok]
        end = p[:2] + r[ok, None] * np.column_stack([np.cos(heading), np.sin(heading)])
        yield np.broadcast_to(p[:2], (int(ok.sum()), 2)), end


def _chunks(
    beams: Iterable[tuple[FloatArray, FloatArray]], size: int
) -> Iterator[tuple[FloatArray, FloatArray]]:
    """The scans' beams stacked in chunks of about ``size`` (whole scans each)."""
    starts: list[FloatArray] = []
    ends: list[FloatArray] = []
    count = 0
    for start, end in beams:
        starts.append(start)
        ends.append(end)
        count += len(end)
        if count >= size:
            yield np.vstack(starts), np.vstack(ends)
            starts, ends, count = [], [], 0
    if count:
        yield np.vstack(starts), np.vstack(ends)


def build_from_carmen(
    log_path: str | Path,
    *,
    resolution: float = 0.05,
    max_range: float = DEFAULT_MAX_RANGE,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.25,
    min_observations: int = 1,
) -> OccupancyGrid:
    """Build an occupancy grid from a CARMEN log's ``FLASER`` scans at their logged poses.

    Args:
        log_path: the log, plain or gzip-compressed.
        resolution: cell size, metres.
        max_range: ranges at or above this are no return, metres.
        occupied_thresh: hit ratio above which a cell is occupied.
        free_thresh: hit ratio below which a cell is free.
        min_observations: cells seen fewer times are unknown.

    Raises:
        MapImportError: unreadable or malformed log, or no beam with a return.
    """
    log = read_carmen(log_path, max_range=max_range)
    return build_grid(
        log.scans,
        resolution=resolution,
        occupied_thresh=occupied_thresh,
        free_thresh=free_thresh,
        min_observations=min_observations,
    )
