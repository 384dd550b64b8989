"""The methods compared, behind one interface, and the loop that runs one on one run.

Every method starts from the run's first reference pose and gets, per scan, the odometry
motion since the previous scan and the scan, exactly as :class:`rlutf.Localizer` does in the
service. Only the ``update`` call is timed; building per-map structures (the ICP k-d tree,
AMCL's likelihood field) happens before, once per map, as a deployment would at start-up.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from bench.baselines import AmclConfig, Estimate, IcpConfig, ParticleFilter, PointToLineIcp
from bench.scenarios import FloatArray, Run
from rlutf.localizer import Localizer, LocalizerConfig
from rlutf.map import Map
from rlutf.motion import compose, relative
from rlutf.scan import Scan


class Tracker(Protocol):
    """One robot's pose tracker."""

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """Take the motion since the previous scan and the new scan; return the pose."""
        ...


Factory = Callable[[Map, FloatArray, int], Tracker]


@dataclass(frozen=True)
class Method:
    """A named way of tracking a robot.

    Attributes:
        name: short id (command line, file names).
        label: name in tables and plots.
        make: builds a tracker from the map, the initial pose and a seed.
        prepare: builds what the tracker needs per map, untimed (optional).
    """

    name: str
    label: str
    make: Factory
    prepare: Callable[[Map], object] | None = None


class DeadReckoning:
    """Odometry only: the pose every other method starts its correction from."""

    def __init__(self, pose: FloatArray) -> None:
        self._pose = np.asarray(pose, dtype=np.float64).copy()

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """Compose the motion; ignore the scan."""
        self._pose = compose(self._pose, motion)
        return Estimate(self._pose.copy(), "predicted")


class RlutfTracker:
    """:class:`rlutf.Localizer` behind the tracker interface.

    Args:
        world: the map.
        pose: initial pose.
        config: the localizer's parameters.
        seed: the localizer's seed.
        spread: ``(metres, radians)``: how far off ``pose`` may be (``None``: the config's
            default for an operator's pose).
    """

    def __init__(
        self,
        world: Map,
        pose: FloatArray,
        config: LocalizerConfig,
        seed: int,
        spread: tuple[float, float] | None = None,
    ) -> None:
        self._localizer = Localizer(world, pose, config, seed=seed, spread=spread)

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """One RLuTF update."""
        result = self._localizer.update(motion, scan)
        return Estimate(result.pose, result.status, result.covariance)


def _rlutf(config: LocalizerConfig) -> Factory:
    def make(world: Map, pose: FloatArray, seed: int) -> Tracker:
        return RlutfTracker(world, pose, config, seed)

    return make


def rlutf_configs() -> dict[str, LocalizerConfig]:
    """The RLuTF configurations compared, by method name."""
    return {
        "paper": LocalizerConfig.paper(),
        "paper-area": LocalizerConfig.paper_area(),
        "norefine": LocalizerConfig(refine=False),
        "nowide": LocalizerConfig(wide_search=False),
        "fixedcap": LocalizerConfig(wide_search=False, cap_per_radius=0.0),
        "default": LocalizerConfig(),
        "turning": LocalizerConfig(discrepancy="turning"),
        "combined": LocalizerConfig(discrepancy="combined"),
    }


#: Labels of the RLuTF methods.
RLUTF_LABELS = {
    "paper": "RLuTF mode=paper (turning functions)",
    "paper-area": "RLuTF mode=paper, area",
    "norefine": "RLuTF default, no refinement",
    "nowide": "RLuTF default, no distance-field search (cap widened with the radius)",
    "fixedcap": "RLuTF default, no distance-field search, fixed 10 cm cap",
    "default": "RLuTF default",
    "turning": "RLuTF turning",
    "combined": "RLuTF combined",
}
#: Methods of the accuracy tables when none are named (``turning`` and ``combined`` only on
#: request, with ``--methods``).
TABLE_METHODS = ("odometry", "paper", "paper-area", "norefine", "default", "icp", "amcl")


def _prepare_icp(world: Map) -> object:
    from bench.baselines.icp import wall_samples

    return wall_samples(world, IcpConfig().spacing)


def _prepare_amcl(world: Map) -> object:
    from bench.baselines.amcl import likelihood_field

    cfg = AmclConfig()
    return likelihood_field(world, cfg.resolution, cfg.laser_likelihood_max_dist)


def all_methods(amcl: AmclConfig | None = None) -> list[Method]:
    """Every method there is, dead reckoning first (see :data:`TABLE_METHODS` for the default
    selection)."""
    amcl_cfg = amcl or AmclConfig()
    out = [Method("odometry", "dead reckoning", lambda w, p, s: DeadReckoning(p))]
    out += [Method(n, RLUTF_LABELS[n], _rlutf(c)) for n, c in rlutf_configs().items()]
    out += [
        Method("icp", "ICP point-to-line", lambda w, p, s: PointToLineIcp(w, p), _prepare_icp),
        Method(
            "amcl",
            "AMCL likelihood field",
            lambda w, p, s: ParticleFilter(w, p, amcl_cfg, seed=s),
            _prepare_amcl,
        ),
    ]
    return out


def table_methods(names: Sequence[str] | None = None) -> list[Method]:
    """The methods named (``None``: :data:`TABLE_METHODS`), in table order; the default
    always included."""
    wanted = set(TABLE_METHODS if names is None else names) | {DEFAULT_METHOD}
    return [m for m in all_methods() if m.name in wanted]


#: The method the issue's targets are about.
DEFAULT_METHOD = "default"


@dataclass(frozen=True, eq=False)
class Trace:
    """What one method did on one run.

    Attributes:
        method: the method's name.
        poses: ``(U, 3)`` the pose after each update (NaN where none was given).
        status: ``(U,)`` the status of each update.
        seconds: ``(U,)`` wall-clock time of each update.
        covariances: ``(U, 3, 3)`` the covariance given with each pose (NaN where none was),
            or ``None`` for a method that gives none.
    """

    method: str
    poses: FloatArray
    status: tuple[str, ...]
    seconds: FloatArray
    covariances: FloatArray | None = None


def track(
    method: Method,
    run: Run,
    seed: int = 0,
    on_update: Callable[[], None] | None = None,
    start: FloatArray | None = None,
) -> Trace:
    """Run ``method`` over ``run`` and time each update.

    Args:
        method: the method.
        run: the run.
        seed: seed of the method's generator.
        on_update: called after every update (progress bars).
        start: the initial pose given to the method (default: the run's ``truth[0]``).
    """
    if method.prepare is not None:
        method.prepare(run.world)
    pose0 = run.truth[0] if start is None else np.asarray(start, dtype=np.float64)
    tracker = method.make(run.world, pose0.copy(), seed)
    count = run.updates
    poses = np.full((count, 3), math.nan)
    covs = np.full((count, 3, 3), math.nan)
    any_cov = False
    seconds = np.empty(count)
    status: list[str] = []
    clock = time.perf_counter
    for k in range(1, count + 1):
        motion = relative(run.odometry[k - 1], run.odometry[k])
        scan = run.scans[k]
        t0 = clock()
        est = tracker.update(motion, scan)
        seconds[k - 1] = clock() - t0
        if est.pose is not None and np.isfinite(est.pose).all():
            poses[k - 1] = est.pose
        if est.covariance is not None:
            covs[k - 1] = est.covariance
            any_cov = True
        status.append(est.status)
        if on_update is not None:
            on_update()
    return Trace(method.name, poses, tuple(status), seconds, covs if any_cov else None)


_WARM: set[str] = set()


def warm_up(methods: Sequence[Method], run: Run, updates: int = 3) -> None:
    """Run each method (once per process) over the first ``updates`` updates of ``run``,
    untimed, so that compiling or loading its kernels (numba) is not timed as an update."""
    short = replace(
        run,
        stamps_ns=run.stamps_ns[: updates + 1],
        truth=run.truth[: updates + 1],
        odometry=run.odometry[: updates + 1],
        scans=run.scans[: updates + 1],
        people=None if run.people is None else run.people[: updates + 1],
    )
    for m in methods:
        if m.name not in _WARM:
            track(m, short, seed=run.seed)
            _WARM.add(m.name)
