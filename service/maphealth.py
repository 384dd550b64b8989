"""Map health in the service: evidence beside the localizer, merged per map, reported.

Two parts, both pure and clock-free, shaped like :class:`service.engine.FleetEngine`:

* :class:`ScanEvidence` sits in every :class:`FleetEngine` (in the worker processes, and in
  replay): each scan at a pose that fits well (not ``lost``, score at least ``min_score``,
  deviation range at most ``max_range``) is counted into a :class:`rlutf.mapchange.ChangeGrid`
  of its map version, from the ranges the localizer cast anyway. :meth:`ScanEvidence.take`
  hands the grids counted since the last call on (and starts empty ones).
* :class:`MapHealthEngine` (the main process, and replay) merges the grids handed on, one
  merged grid per map, reset by a new map version, and says when to publish: a MapHealth per
  map whose evidence changed, at most once per ``interval_ns`` of receive time.

A grid is sums, ORs, minima and maxima of its scans' evidence, so the merged grid is the same
whatever worker counted which scan and in what order grids are merged: the live service and a
replay of its log hold the same grid, bit for bit, once they have counted the same scans, and
give the same MapHealth for it.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from rlutf.localizer import LocalizeResult
from rlutf.map import Map as World
from rlutf.mapchange import Change, ChangeGrid, ChangeSettings, GridCounts, find_changes
from schemas import MapHealth, encode
from schemas.maphealth import MapChange
from service.keys import Keys

#: Poses that count: not lost, at least this score ...
MIN_SCORE = 0.8
#: ... and at most this deviation range, metres.
MAX_RANGE = 0.1


@dataclass(frozen=True)
class Handed:
    """The evidence of one map version counted since the last hand-over (small to pickle: the
    touched cells only, no map)."""

    map_id: str
    version: int
    counts: GridCounts


class ScanEvidence:
    """Counts the scans of well-localized poses into a grid per map version (one engine's).

    Args:
        settings: the grids' parameters.
        min_score: a pose counts from this localization score ...
        max_range: ... and up to this deviation range, metres.
    """

    def __init__(
        self,
        settings: ChangeSettings | None = None,
        min_score: float = MIN_SCORE,
        max_range: float = MAX_RANGE,
    ) -> None:
        self.settings = settings or ChangeSettings()
        self.min_score = min_score
        self.max_range = max_range
        self._grids: dict[tuple[str, int], ChangeGrid] = {}
        # Different robots' scans may be counted from different threads (a worker's pool).
        self._lock = threading.Lock()

    def observe(
        self,
        map_id: str,
        version: int,
        world: World,
        robot: str,
        stamp_ns: int,
        result: LocalizeResult,
    ) -> bool:
        """Count one scan's result if its pose fits well; whether it was counted."""
        if (
            result.status == "lost"
            or result.returns is None
            or result.score < self.min_score
            or not result.deviation_range <= self.max_range
        ):
            return False
        key = (map_id, version)
        with self._lock:
            grid = self._grids.get(key)
            if grid is None or grid.world is not world:
                # an older version's grid has been handed on: nothing more comes for it
                for old in [k for k in self._grids if k[0] == map_id and k[1] < version]:
                    if not self._grids[old].scans:
                        del self._grids[old]
                grid = self._grids[key] = ChangeGrid(world, self.settings)
            grid.add(result.returns, stamp_ns, robot)
        return True

    def take(self) -> list[Handed]:
        """The grids with scans counted since the last call, in map order; counting starts
        afresh (the cells handed on are zeroed, the grids kept)."""
        out = []
        with self._lock:
            for (map_id, version), grid in sorted(self._grids.items()):
                if grid.scans:
                    snapshot = grid.snapshot()
                    grid.clear(snapshot.cells)
                    out.append(Handed(map_id, version, snapshot))
        return out


class NullEvidence(ScanEvidence):
    """Map health off: nothing is counted."""

    def observe(
        self,
        map_id: str,
        version: int,
        world: World,
        robot: str,
        stamp_ns: int,
        result: LocalizeResult,
    ) -> bool:
        """Count nothing."""
        return False


@dataclass
class _MapState:
    version: int
    world: World
    grid: ChangeGrid | None = None
    changed: bool = False
    last_put_ns: int | None = None
    last_payload: bytes | None = None
    report: bytes | None = None  # the newest MapHealth made, answered to gets
    report_ns: int | None = None  # when it was made (receive time), if known


@dataclass(frozen=True)
class HealthOut:
    """A MapHealth to put on ``key`` and record (``stamp_ns``: its own stamp)."""

    key: str
    map_id: str
    payload: bytes
    stamp_ns: int


@dataclass
class MapHealthEngine:
    """The merged evidence of every map, and its MapHealth.

    Args:
        keys: the key layout.
        interval_ns: least time between two MapHealth puts of one map (receive time).
    """

    keys: Keys
    interval_ns: int = 1_000_000_000
    settings: ChangeSettings = field(default_factory=ChangeSettings)
    _maps: dict[str, _MapState] = field(default_factory=dict)

    def version(self, map_id: str) -> int | None:
        """The map version the evidence of ``map_id`` is about, if any is registered."""
        state = self._maps.get(map_id)
        return None if state is None else state.version

    def register_map(self, map_id: str, version: int, world: World) -> None:
        """A map version is loaded: a newer one starts the map's evidence afresh."""
        state = self._maps.get(map_id)
        if state is not None and version <= state.version:
            return
        self._maps[map_id] = _MapState(version, world)

    def merge(self, handed: list[Handed]) -> None:
        """Add grids handed on by :meth:`ScanEvidence.take`; those of a version other than the
        map's current one are dropped (an older version's evidence says nothing of the new)."""
        for h in handed:
            state = self._maps.get(h.map_id)
            if state is None or h.version != state.version:
                continue
            if state.grid is None:
                state.grid = ChangeGrid(state.world, self.settings)
            state.grid.merge(h.counts)
            state.changed = True

    def due(self, now_ns: int, reports: Callable[[str], bool] | None = None) -> list[HealthOut]:
        """The MapHealth of every map whose evidence changed and whose last put is at least
        ``interval_ns`` before ``now_ns`` (and whose report differs from the last put); with
        ``reports``, only of the maps whose MapHealth key it says this engine reports."""
        out: list[HealthOut] = []
        for map_id in sorted(self._maps):
            state = self._maps[map_id]
            if not state.changed or state.grid is None:
                continue
            if reports is not None and not reports(self.keys.maphealth(map_id)):
                continue
            if state.last_put_ns is not None and now_ns - state.last_put_ns < self.interval_ns:
                continue
            state.changed = False
            payload = self._report(map_id, state)
            state.report, state.report_ns = payload, now_ns
            if payload == state.last_payload:
                continue
            state.last_payload, state.last_put_ns = payload, now_ns
            out.append(
                HealthOut(self.keys.maphealth(map_id), map_id, payload, state.grid.newest_ns)
            )
        return out

    def answer(self, map_id: str, now_ns: int | None = None) -> bytes | None:
        """The current MapHealth of a map (for a get), or ``None`` when nothing was counted.

        Given ``now_ns``, a report made less than ``interval_ns`` before is answered again
        (making one walks the whole grid: a flood of gets must not make one each), as puts
        are at most once per ``interval_ns``."""
        state = self._maps.get(map_id)
        if state is None or state.grid is None:
            return None
        fresh = (
            now_ns is not None
            and state.report_ns is not None
            and now_ns - state.report_ns < self.interval_ns
        )
        if state.report is None or (state.changed and not fresh):
            state.report, state.report_ns = self._report(map_id, state), now_ns
        return state.report

    def map_ids(self) -> list[str]:
        """Maps with evidence."""
        return sorted(m for m, s in self._maps.items() if s.grid is not None)

    @staticmethod
    def _report(map_id: str, state: _MapState) -> bytes:
        grid = state.grid
        assert grid is not None
        message = MapHealth(
            map_id=map_id,
            version=state.version,
            stamp_ns=grid.newest_ns,
            since_ns=grid.oldest_ns,
            scans=grid.scans,
            robots=len(grid.robot_ids),
            changes=tuple(wire_change(c) for c in find_changes(grid)),
        )
        return encode(message)


def wire_change(change: Change) -> MapChange:
    """A :class:`rlutf.mapchange.Change` as its wire model (coordinates rounded to 1 mm)."""
    geometry = _rounded(change.geometry.__geo_interface__)
    return MapChange.model_validate(
        {
            "kind": change.kind,
            "geometry": geometry,
            "evidence": change.evidence,
            "robots": change.robots,
            "first_ns": change.first_ns,
            "last_ns": change.last_ns,
            "confidence": change.confidence,
        }
    )


def _rounded(geo: object) -> object:
    if isinstance(geo, dict):
        return {k: _rounded(v) for k, v in geo.items()}
    if isinstance(geo, list | tuple):
        return [_rounded(v) for v in geo]
    if isinstance(geo, float):
        return round(geo, 3) if math.isfinite(geo) else geo
    return geo
