"""The accuracy benchmark: every method on every scenario's runs, same inputs, one process.

:func:`build_runs` simulates the named scenarios (and loads the real CARMEN logs);
:func:`run_accuracy` tracks every run with every method, computes each scan's Cramer-Rao
bound at its true pose, and pools the runs of a scenario into one :class:`Summary` per
method.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from bench.carmen import LOGS, REAL_RUNS, carmen_run
from bench.crb import run_bounds
from bench.measures import Summary, summarise
from bench.methods import Method, Trace, track, warm_up
from bench.scenarios import DATA, FloatArray, Run, Scenario, named_scenarios, simulate


@dataclass(frozen=True)
class Profile:
    """How much to run.

    Attributes:
        name: ``"full"`` or ``"quick"``.
        steps: scans per simulated run.
        seeds: seeds of the simulated runs of each scenario.
        carmen_limit: scans kept of each CARMEN log (``None``: all).
        speed_beams: beam counts of the latency sweep.
        speed_updates: updates per point of the latency sweeps.
        map_sizes: procedural buildings of the map-size sweep, ``(width, height, rooms_x,
            rooms_y)``.
        real_maps: include the imported and CARMEN maps in the map-size sweep.
    """

    name: str
    steps: int
    seeds: tuple[int, ...]
    carmen_limit: int | None
    speed_beams: tuple[int, ...]
    speed_updates: int
    map_sizes: tuple[tuple[float, float, int, int], ...]
    real_maps: bool


FULL = Profile(
    "full",
    steps=250,
    seeds=(1, 2),
    carmen_limit=None,
    speed_beams=(90, 180, 360, 720, 1440),
    speed_updates=100,
    map_sizes=((12.0, 7.0, 2, 1), (24.0, 14.0, 3, 2), (48.0, 28.0, 6, 4), (96.0, 56.0, 12, 8)),
    real_maps=True,
)
QUICK = Profile(
    "quick",
    steps=40,
    seeds=(1,),
    carmen_limit=25,
    speed_beams=(90, 360, 1440),
    speed_updates=10,
    map_sizes=((12.0, 7.0, 2, 1), (48.0, 28.0, 6, 4)),
    real_maps=False,
)

#: Descriptions of the real runs, by log name.
_ODOM5 = (
    "odometry made from the SLAM poses' increments, 5 % noise and a heading bias of "
    "0.02 rad/m (seeded)"
)
REAL = {
    "intel": "Intel lab (CARMEN log): map built from the corrected scans, the log's own "
    "odometry, 180 beams over 180 degrees",
    "intel-odom5": f"Intel lab (CARMEN log), same scans and map, {_ODOM5}",
    "aces": "ACES building (CARMEN log): map built from the corrected scans, the log's own "
    "odometry, 180 beams over 180 degrees",
    "aces-odom5": f"ACES building (CARMEN log), same scans and map, {_ODOM5}",
}


@dataclass
class ScenarioResult:
    """Every method on every run of one scenario.

    Attributes:
        name: the scenario.
        description: one line.
        runs: the runs.
        bounds: per run, ``(U,)`` per-scan Cramer-Rao bounds, metres.
        traces: per method name, one trace per run.
        summaries: per method name, the pooled measures.
    """

    name: str
    description: str
    runs: list[Run]
    bounds: list[FloatArray] = field(default_factory=list)
    traces: dict[str, list[Trace]] = field(default_factory=dict)
    summaries: dict[str, Summary] = field(default_factory=dict)

    @property
    def real(self) -> bool:
        """Whether the runs are real logs (reference poses from SLAM, not ground truth)."""
        return self.name in REAL


def has_data(world: str) -> bool:
    """Whether the data a world needs is there (procedural buildings need none)."""
    if world in ("building", "rooms"):
        return True
    if world in REAL_RUNS:
        world = REAL_RUNS[world][0]
    if world in LOGS:
        return (DATA / "carmen" / f"{world}-corrected.log.gz").exists()
    return (DATA / "maps" / f"{world}.yaml").exists()


def scenario_list(profile: Profile) -> list[Scenario]:
    """The simulated scenarios of a profile."""
    return named_scenarios(profile.steps)


def build_runs(
    profile: Profile, only: Sequence[str] | None = None, real: bool = True
) -> list[ScenarioResult]:
    """Simulate (or load) the runs of every scenario, without tracking them yet.

    Scenarios whose data (``bench/data/maps``, ``bench/data/carmen``) is missing are
    left out.

    Args:
        profile: sizes.
        only: scenario names to keep (``None``: all).
        real: include the CARMEN logs.
    """
    out = []
    for sc in scenario_list(profile):
        if not has_data(sc.world):
            continue
        if only is None or sc.name in only:
            runs = [simulate(sc, seed) for seed in profile.seeds]
            out.append(ScenarioResult(sc.name, sc.description, runs))
    if real:
        out += [
            ScenarioResult(name, REAL[name], [carmen_run(log, profile.carmen_limit, kind)])
            for name, (log, kind) in REAL_RUNS.items()
            if (only is None or name in only) and has_data(name)
        ]
    return out


def run_accuracy(
    results: list[ScenarioResult],
    methods: Sequence[Method],
    on_update: Callable[[], None] | None = None,
) -> list[ScenarioResult]:
    """Track every run with every method and summarise; fills ``results`` in place.

    Args:
        results: from :func:`build_runs`.
        methods: the methods, in table order.
        on_update: called after every update of every method (progress).
    """
    if results and results[0].runs:
        warm_up(methods, results[0].runs[0])
    for res in results:
        res.bounds = [run_bounds(r.world, r.truth, r.scans, r.sigma) for r in res.runs]
        for m in methods:
            res.traces[m.name] = [track(m, r, seed=r.seed, on_update=on_update) for r in res.runs]
            traces = res.traces[m.name]
            res.summaries[m.name] = summarise(
                [t.poses for t in traces],
                [r.truth[1:] for r in res.runs],
                [t.status for t in traces],
                [t.seconds for t in traces],
                res.bounds,
                [t.covariances for t in traces],
            )
    return results


def total_updates(results: Sequence[ScenarioResult], methods: Sequence[Method]) -> int:
    """Updates :func:`run_accuracy` will run (for a progress bar)."""
    return len(methods) * sum(r.updates for res in results for r in res.runs)
