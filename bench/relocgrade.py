"""Running and grading the relocalization cases (:mod:`bench.relocalize`): one graded call per
query and setting, the counts per map, the search grid's cost."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from shapely.geometry import box

from bench.reloccases import (
    COARSE,
    REFINED,
    SETTINGS,
    MapCase,
    Oracle,
    close,
    oracle,
    queries,
)
from bench.scenarios import FloatArray
from rlutf.map import Map
from rlutf.relocalize import Relocalization, RelocalizeSettings, relocalize, search_grid
from rlutf.scan import Scan
from rlutf.sim import LidarModel, simulate_scan


@dataclass(frozen=True, eq=False)
class Case:
    """One relocalization graded.

    Attributes:
        map: the map's name.
        setting: ``default`` or ``turning``.
        truth: ``(3,)`` the true pose.
        scan: the scan.
        result: what :func:`relocalize` returned.
        cpu: CPU seconds of the call.
        wall: wall seconds of the call.
        oracle: the ambiguity ground truth.
    """

    map: str
    setting: str
    truth: FloatArray
    scan: Scan
    result: Relocalization
    cpu: float
    wall: float
    oracle: Oracle

    @property
    def confident(self) -> bool:
        """The first answer has status ``corrected`` (found and not ambiguous)."""
        return self.result.found and not self.result.ambiguous

    def _best_close(self, tol: tuple[float, float]) -> bool:
        best = self.result.best
        return best is not None and close(best.pose, self.truth, *tol)

    @property
    def coarse(self) -> bool:
        """Confident and within 0.3 m / 5 deg."""
        return self.confident and self._best_close(COARSE)

    @property
    def refined(self) -> bool:
        """Confident and within 5 cm / 1 deg."""
        return self.confident and self._best_close(REFINED)

    @property
    def wrong(self) -> bool:
        """Confident and not within 0.3 m / 5 deg."""
        return self.confident and not self._best_close(COARSE)

    @property
    def truth_listed(self) -> bool:
        """The truth (0.3 m / 5 deg) is among the hypotheses."""
        return any(close(h.pose, self.truth, *COARSE) for h in self.result.hypotheses)


@dataclass(frozen=True)
class Summary:
    """A map's cases under one setting."""

    map: str
    setting: str
    cases: int
    ambiguous: int
    coarse: int
    refined: int
    wrong: int
    listed: int
    flagged: int
    not_found: int
    cpu_median: float
    cpu_p95: float
    cpu_max: float
    wall_median: float

    @property
    def clear(self) -> int:
        """Cases the oracle calls non-ambiguous."""
        return self.cases - self.ambiguous


def summarise(cases: Sequence[Case]) -> Summary:
    """The counts and times of one map's cases under one setting."""
    cpu = np.array([c.cpu for c in cases]) if cases else np.full(1, math.nan)
    wall = np.array([c.wall for c in cases]) if cases else np.full(1, math.nan)
    clear = [c for c in cases if not c.oracle.ambiguous]
    amb = [c for c in cases if c.oracle.ambiguous]
    return Summary(
        cases[0].map if cases else "",
        cases[0].setting if cases else "",
        len(cases),
        len(amb),
        sum(c.coarse for c in clear),
        sum(c.refined for c in clear),
        sum(c.wrong for c in cases),
        sum(c.truth_listed for c in amb),
        sum(c.result.ambiguous for c in cases),
        sum(not c.result.found for c in cases),
        float(np.median(cpu)),
        float(np.percentile(cpu, 95)),
        float(np.max(cpu)),
        float(np.median(wall)),
    )


@dataclass(frozen=True)
class Precompute:
    """The search grid of one map, made on a fresh map object."""

    map: str
    area: float
    cells: int
    nbytes: int
    cpu: float
    wall: float
    cached: float


def precompute(case: MapCase, settings: RelocalizeSettings | None = None) -> Precompute:
    """Time and memory of the map's search grid, first call on a fresh :class:`Map` (and the
    cached second call)."""
    cfg = settings or RelocalizeSettings()
    fresh = Map.from_shapely(case.world.geometry)
    c0, w0 = time.process_time(), time.perf_counter()
    grid = search_grid(fresh, cfg)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    w1 = time.perf_counter()
    search_grid(fresh, cfg)
    cached = time.perf_counter() - w1
    cells = int(grid.levels.shape[1] * grid.levels.shape[2])
    return Precompute(case.name, case.area, cells, grid.nbytes, cpu, wall, cached)


def run_map(
    case: MapCase, count: int, on_case: Callable[[], None] = lambda: None
) -> tuple[dict[str, list[Case]], Precompute]:
    """Every query of a map under both settings, graded with one oracle per query."""
    pre = precompute(case)
    search_grid(case.world, SETTINGS["default"])  # the cache the calls below use
    out: dict[str, list[Case]] = {name: [] for name in SETTINGS}
    for truth, scan in queries(case, count):
        runs = {}
        for name, cfg in SETTINGS.items():
            c0, w0 = time.process_time(), time.perf_counter()
            result = relocalize(case.world, scan, settings=cfg)
            runs[name] = (result, time.process_time() - c0, time.perf_counter() - w0)
            on_case()
        candidates = [h.pose for r, _, _ in runs.values() for h in r.hypotheses]
        truth_oracle = oracle(case.world, scan, truth, candidates)
        for name, (result, cpu, wall) in runs.items():
            out[name].append(Case(case.name, name, truth, scan, result, cpu, wall, truth_oracle))
    return out, pre


def warm_up() -> None:
    """Compile the kernels (numba caches) on a tiny map, so no timing pays for it."""
    world = Map.from_shapely(box(0.0, 0.0, 4.0, 3.0).difference(box(1.0, 1.0, 1.5, 1.5)))
    rng = np.random.default_rng(0)
    scan = simulate_scan(world, np.array([2.5, 2.0, 0.3]), LidarModel(), rng)
    for cfg in SETTINGS.values():
        relocalize(world, scan, settings=cfg)
