"""Where the world no longer matches the map: evidence from scans at good poses, and reports.

Per scan (:meth:`ChangeGrid.add`, beside the localizer, from the ranges it cast anyway): a
return well short of the range the map predicts hit something the map lacks (*short*: its cell
is marked at the return); a return well beyond it went through a wall the map has (*through*:
the cell of the map's wall is marked); every few beams count the cells they crossed as seen
free. Only scans at poses that fit well count (the caller decides), so a mislocalized robot's
scans say nothing.

Over all robots (:class:`ChangeGrid`): per cell of a fixed grid over the map, for each kind, the
returns that marked it, the time windows they fell in (a 31-bit mask of ``stamp // window`` mod
31), the robots (a 31-bit mask of a hash of the robot id), and the first and last stamps; and
the free passes. Every update is a sum, an OR, a min or a max: the grid is the same whatever
order the scans come in, so the live service (scans from several worker processes, merged with
:meth:`ChangeGrid.merge`) and replay (scans in log order) hold the same grid once they have
counted the same scans. Its size is fixed by the map.

:func:`find_changes` reports the places where the disagreement persists across time: cells
marked in at least ``min_windows`` windows spanning ``min_span_s`` seconds, densely, and (short
cells) occupied when seen (a person walking through is in a cell for a scan or three, and the
cell is seen free far more often; a rack's face stops most beams that reach it). Short cells
near the map's walls are left out (a map traced from a log is a few centimetres off along every
wall), as are through cells not on a wall.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import LineString, MultiLineString, MultiPolygon, Polygon, box

from rlutf._unionfind import group_roots
from rlutf.map import Map

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SHORT, THROUGH = 0, 1
#: The most a count holds: a map version's grid only ever adds, for months, and a busy cell
#: passes 2^31 (a count that wrapped went negative: a place vanished from the report, or a cell
#: seen free looked occupied); it stays here instead. A sum of counts that are never negative,
#: held at the top, is the same in any order.
TOP = 2**31 - 1
_NEVER = np.iinfo(np.int64).max
#: Robot ids a grid remembers at most (its MapHealth's ``robots`` then stays at this number).
#: Merged evidence names robots by id, and any client can put evidence on the bus: 20 payloads
#: of 100,000 made-up ids each (93 kB apiece compressed) held 2,000,000 ids, +330 MB, and
#: more payloads would have held more until the service ran out of memory.
ROBOT_IDS_MAX = 100_000


@dataclass(frozen=True)
class Returns:
    """The returns of one scan as the localizer compared them at its pose.

    Attributes:
        pose: ``(3,)`` the robot base's pose.
        offset: ``(3,)`` the sensor's pose in the base frame.
        cos: ``(N,)`` cosines of the beams with a return (sensor frame).
        sin: ``(N,)`` their sines.
        measured: ``(N,)`` measured ranges, metres.
        cast: ``(N,)`` ranges cast on the map from ``pose``, metres (``inf``: no wall hit).
    """

    pose: FloatArray
    offset: FloatArray
    cos: FloatArray
    sin: FloatArray
    measured: FloatArray
    cast: FloatArray


@dataclass(frozen=True)
class ChangeSettings:
    """Parameters of the evidence and of the reports.

    Attributes:
        cell: grid cell side, metres.
        margin: the grid extends this far past the map's bounds, metres.
        tolerance: a return counts when it is this much shorter or longer than the map's
            range, metres.
        window_s: length of a time window, seconds.
        free_stride: every this many beams count the cells they cross as seen free.
        occupied: a short cell counts only when at least this share of the beams that reached
            it ended there (a person's path is seen free far more often than not) ...
        cell_windows: ... and it was marked in this many windows ...
        min_windows: a change is reported once it was seen in this many windows ...
        min_span_s: ... spanning at least this long, seconds.
        min_density: ... and its cells were marked by this many returns per window they were
            marked in (a person walking by marks a cell in one to three scans).
        min_evidence: ... and by this many returns in all (summed over its cells).
        clearance: short cells closer than this to a map wall are not reported, metres.
        wall_distance: through cells farther than this from a map wall are not reported.
        min_area: smallest ``added`` region reported, m^2.
        min_length: shortest ``removed`` wall reported, metres.
    """

    cell: float = 0.2
    margin: float = 1.0
    tolerance: float = 0.3
    window_s: float = 5.0
    free_stride: int = 8
    occupied: float = 0.5
    cell_windows: int = 2
    min_windows: int = 3
    min_span_s: float = 20.0
    min_density: float = 4.0
    min_evidence: int = 40
    clearance: float = 0.25
    wall_distance: float = 0.3
    min_area: float = 0.08
    min_length: float = 0.4


@dataclass(frozen=True)
class Change:
    """One place where the world and the map disagree.

    Attributes:
        kind: ``"added"`` (something the map lacks) or ``"removed"`` (a wall beams pass).
        geometry: a Polygon or MultiPolygon (added), a LineString or MultiLineString (removed).
        evidence: returns that marked its cells, summed over the cells.
        robots: distinct robots that saw it (by a hash of the ids into 31 bits: at most 31).
        first_ns: stamp of the first scan that marked it.
        last_ns: stamp of the last.
        confidence: in [0, 1]: rises with the evidence, the windows and the robots.
    """

    kind: str
    geometry: Polygon | MultiPolygon | LineString | MultiLineString
    evidence: int
    robots: int
    first_ns: int
    last_ns: int
    confidence: float


def robot_bit(robot_id: str) -> int:
    """The bit of a robot in the robot masks (a hash of the id, stable across processes)."""
    import zlib

    return 1 << (zlib.crc32(robot_id.encode()) % 31)


@dataclass(frozen=True, eq=False)
class GridCounts:
    """What a grid counted, in the cells it touched: to hand it to another process.

    Attributes:
        shape: ``(nx, ny)`` of the grid.
        cells: ``(K,)`` flat indices of the cells with any count.
        counts: ``(7, K)`` the grid's counts there.
        times: ``(4, K)`` its first and last stamps there.
        scans: scans counted.
        oldest_ns: stamp of the first scan counted.
        newest_ns: stamp of the last.
        robot_ids: robots whose scans were counted.
    """

    shape: tuple[int, int]
    cells: IntArray
    counts: NDArray[np.int32]
    times: NDArray[np.int64]
    scans: int
    oldest_ns: int
    newest_ns: int
    robot_ids: frozenset[str]


@dataclass
class ChangeGrid:
    """The evidence of one map version, over all robots.

    Args:
        world: the map.
        settings: parameters.
    """

    world: Map
    settings: ChangeSettings = field(default_factory=ChangeSettings)

    def __post_init__(self) -> None:
        s = self.settings
        minx, miny, maxx, maxy = self.world.bounds
        self.origin = (minx - s.margin, miny - s.margin)
        self.nx = math.ceil((maxx - minx + 2 * s.margin) / s.cell)
        self.ny = math.ceil((maxy - miny + 2 * s.margin) / s.cell)
        n = self.nx * self.ny
        # one block of counts and one of stamps: the kernel takes two arrays, not eleven
        self.counts = np.zeros((7, n), dtype=np.int32)
        self.times = np.zeros((4, n), dtype=np.int64)
        self.times[:2] = _NEVER
        self.marks = self.counts[0:2]
        self.free = self.counts[2]
        self.windows = self.counts[3:5]
        self.robots = self.counts[5:7]
        self.first = self.times[0:2]
        self.last = self.times[2:4]
        self.oldest_ns = _NEVER  # stamps of the first and last scan counted
        self.newest_ns = 0
        self.robot_ids: set[str] = set()
        # the kernel's constants, made once
        self._reals = np.array([s.tolerance, 0.25 * s.cell, *self.origin, s.cell])
        self._ints = np.array([s.free_stride, self.nx, self.ny], dtype=np.int64)
        self._window_ns = int(s.window_s * 1e9)
        self._bits: dict[str, int] = {}
        self.scans = 0

    def add(self, returns: Returns, stamp_ns: int, robot: str) -> tuple[int, int]:
        """Count one scan of ``robot``: a return shorter than the map's
        range by more than ``tolerance`` marks the cell it hit (``short``), one longer by more
        than ``tolerance`` the cell of the map's wall it passed (``through``, a quarter cell
        past the map's range, inside the wall); every ``free_stride``-th beam counts the cells
        it crossed as seen free. Returns the beams marked ``(short, through)``."""
        from rlutf import _changes

        r = returns
        window = 1 << ((stamp_ns // self._window_ns) % 31)
        bit = self._bits.get(robot)
        if bit is None:
            bit = self._bits[robot] = robot_bit(robot)
            self.robot_ids.add(robot)
        self.scans += 1
        self.oldest_ns = min(self.oldest_ns, stamp_ns)
        self.newest_ns = max(self.newest_ns, stamp_ns)
        return _changes.observe(
            r.pose, r.offset, r.cos, r.sin, r.measured, r.cast, self._reals, self._ints,
            self.counts, self.times, stamp_ns, window, bit,
        )  # fmt: skip

    def snapshot(self) -> GridCounts:
        """What this grid counted, in the cells it touched."""
        cells = np.flatnonzero(self.counts.any(axis=0))
        return GridCounts(
            (self.nx, self.ny), cells, self.counts[:, cells], self.times[:, cells], self.scans,
            self.oldest_ns, self.newest_ns, frozenset(self.robot_ids),
        )  # fmt: skip

    def merge(self, other: ChangeGrid | GridCounts) -> None:
        """Add another grid of the same map's evidence (another worker's scans) to this one:
        the result is the grid of both grids' scans, whatever the order of the merges."""
        if isinstance(other, ChangeGrid):
            other = other.snapshot()
        if other.shape != (self.nx, self.ny):
            raise ValueError(
                f"grid: cannot merge a {other.shape[0]} x {other.shape[1]} grid into a "
                f"{self.nx} x {self.ny} grid"
            )
        c = other.cells
        # held at TOP, not wrapped
        total = self.counts[0:3, c].astype(np.int64) + other.counts[0:3]
        self.counts[0:3, c] = np.minimum(total, TOP)
        self.counts[3:7, c] |= other.counts[3:7]
        self.times[0:2, c] = np.minimum(self.times[0:2, c], other.times[0:2])
        self.times[2:4, c] = np.maximum(self.times[2:4, c], other.times[2:4])
        self.scans += other.scans
        self.oldest_ns = min(self.oldest_ns, other.oldest_ns)
        self.newest_ns = max(self.newest_ns, other.newest_ns)
        room = ROBOT_IDS_MAX - len(self.robot_ids)
        if len(other.robot_ids) <= room:
            self.robot_ids |= other.robot_ids
        elif room > 0:  # up to the bound, the smallest ids first (the same in any process)
            new = sorted(other.robot_ids - self.robot_ids)
            self.robot_ids.update(new[:room])

    def clear(self, cells: IntArray | None = None) -> None:
        """Forget every scan (after its evidence was handed on with :meth:`merge`); ``cells``:
        the only cells with counts (:attr:`GridCounts.cells`), to clear just those."""
        at = slice(None) if cells is None else cells
        self.counts[:, at] = 0
        self.times[:2, at] = _NEVER
        self.times[2:, at] = 0
        self.scans = 0
        self.oldest_ns = _NEVER
        self.newest_ns = 0
        self.robot_ids = set()
        self._bits = {}

    def empty(self) -> ChangeGrid:
        """A grid of the same map and settings with no scans."""
        return ChangeGrid(self.world, self.settings)

    def centre(self, cells: IntArray) -> FloatArray:
        """``(K, 2)`` centres of flat cells."""
        s = self.settings
        iy, ix = np.divmod(cells, self.nx)
        return np.column_stack(
            [self.origin[0] + (ix + 0.5) * s.cell, self.origin[1] + (iy + 0.5) * s.cell]
        )


def _popcount(masks: NDArray[np.int32]) -> IntArray:
    """Bits set in each mask."""
    bits = np.unpackbits(np.ascontiguousarray(masks, dtype="<i4").view(np.uint8))
    out: IntArray = bits.reshape(*np.shape(masks), 32).sum(axis=-1, dtype=np.int64)
    return out


def _components(cells: IntArray, nx: int) -> list[IntArray]:
    """The 8-connected groups of ``cells`` (flat indices, sorted), each sorted, in order of
    their first cell."""
    index = {int(c): i for i, c in enumerate(cells)}

    def touching() -> Iterator[tuple[int, int]]:
        for i, c in enumerate(cells.tolist()):
            cy, cx = divmod(c, nx)
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if (dy, dx) <= (0, 0) or not 0 <= cx + dx < nx:
                        continue
                    j = index.get((cy + dy) * nx + cx + dx)
                    if j is not None:
                        yield i, j

    groups: dict[int, list[int]] = {}
    for i, r in enumerate(group_roots(len(cells), touching())):
        groups.setdefault(r, []).append(i)
    return [cells[np.array(g)] for _, g in sorted(groups.items())]


@dataclass(frozen=True, eq=False)
class MapWalls:
    """The map's walls as :func:`find_changes` uses them, made once per map version
    (:func:`map_walls`): the boundary of a map of real size takes milliseconds to make, and the
    distance of each cell to it a walk over every wall (0.7 s for 5,000 cells on a 10 MB map).

    Attributes:
        boundary: the boundary of the map's free space (its rings).
        tree: an index of the boundary's parts (one per ring).
    """

    boundary: LineString | MultiLineString
    tree: shapely.STRtree

    def distance(self, points: FloatArray) -> FloatArray:
        """``(K,)`` distance of each point ``(K, 2)`` to the walls: equal, bit for bit, to
        ``shapely.distance(points, boundary)`` (the least of the distances to the rings, each
        computed the same way), with the rings far from a point left out."""
        out = np.empty(len(points))
        if len(points):
            found, distances = self.tree.query_nearest(
                shapely.points(points), return_distance=True, all_matches=False
            )
            out[found[0]] = distances
        return out


def map_walls(world: Map) -> MapWalls:
    """The map's :class:`MapWalls`, kept with the map (:meth:`rlutf.map.Map.derived`)."""

    def make(w: Map) -> MapWalls:
        boundary = w.geometry.boundary
        return MapWalls(boundary, shapely.STRtree(shapely.get_parts(boundary)))

    return world.derived("mapchange:walls", make)


def find_changes(grid: ChangeGrid) -> list[Change]:
    """The changes the grid holds evidence of, ``added`` first, each kind in grid order."""
    s = grid.settings
    world = grid.world
    walls = map_walls(world)
    out: list[Change] = []
    for kind in (SHORT, THROUGH):
        marks = grid.marks[kind]
        seen = np.flatnonzero(marks >= 2)
        if len(seen) == 0:
            continue
        windows = _popcount(grid.windows[kind, seen])
        keep = (windows >= s.cell_windows) & (marks[seen] >= s.min_density * windows)
        if kind == SHORT:
            passed = s.free_stride * grid.free[seen].astype(np.float64)
            keep &= marks[seen] >= s.occupied * (marks[seen] + passed)
        dense = seen[keep]
        if len(dense) == 0:
            continue
        centres = grid.centre(dense)
        distance = walls.distance(centres)
        if kind == SHORT:
            keep = world.contains(centres) & (distance >= s.clearance)
        else:
            keep = distance <= s.wall_distance
        for group in _components(dense[keep], grid.nx):
            change = _change(grid, kind, group)
            if change is not None:
                out.append(change)
    return out


def _change(grid: ChangeGrid, kind: int, cells: IntArray) -> Change | None:
    """The change a group of cells makes, or ``None`` when it is not persistent enough."""
    s = grid.settings
    evidence = int(grid.marks[kind, cells].sum())
    windows = int(_popcount(np.bitwise_or.reduce(grid.windows[kind, cells])))
    robots = int(_popcount(np.bitwise_or.reduce(grid.robots[kind, cells])))
    first, last = int(grid.first[kind, cells].min()), int(grid.last[kind, cells].max())
    if evidence < s.min_evidence or windows < s.min_windows or last - first < s.min_span_s * 1e9:
        return None
    h = 0.5 * s.cell
    boxes = shapely.union_all([box(x - h, y - h, x + h, y + h) for x, y in grid.centre(cells)])
    geometry: Polygon | MultiPolygon | LineString | MultiLineString
    if kind == SHORT:
        # what a robot sees of an object is its faces: the hull of the cells marked
        shape = shapely.convex_hull(boxes)
        if not isinstance(shape, Polygon) or shape.area < s.min_area:
            return None
        geometry = shape
    else:
        walls = map_walls(grid.world).boundary
        line = shapely.line_merge(walls.intersection(boxes.buffer(h)))
        if not isinstance(line, LineString | MultiLineString) or line.length < s.min_length:
            return None
        geometry = line
    confidence = (1.0 - 0.5 ** (evidence / s.min_evidence)) * (
        1.0 - 0.5 ** (windows / s.min_windows)
    )
    return Change(
        "added" if kind == SHORT else "removed",
        geometry,
        evidence,
        robots,
        first,
        last,
        round(min(max(confidence, 0.0), 1.0), 6),
    )
