"""The methods compared, behind one interface, and the loop that runs one on one run.

Every method starts from the run's first reference pose and gets, per scan, the odometry
motion since the previous scan and the scan, exactly as :class:`rlutf.Localizer` does in the
service. Only the ``update`` call is timed; building per-map structures (the ICP k-d tree,
AMCL's likelihood field) happens before, once per map, as a deployment would at start-up.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
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
    """:class:`rlutf.Localizer` behind the tracker interface."""

    def __init__(self, world: Map, pose: FloatArray, config: LocalizerConfig, seed: int) -> None:
        self._localizer = Localizer(world, pose, config, seed=seed)

    def update(self, motion: FloatArray, scan: Scan) -> Estimate:
        """One RLuTF update."""
        result = self._localizer.update(motion, scan)
        return Estimate(result.pose, result.status)


def _rlutf(config: LocalizerConfig) -> Factory:
    def make(world: Map, pose: FloatArray, seed: int) -> Tracker:
        return RlutfTracker(world, pose, config, seed)

    return make


def _prepare_icp(world: Map) -> object:
    from bench.baselines.icp import wall_samples

    return wall_samples(world, IcpConfig().spacing)


def _prepare_amcl(world: Map) -> object:
    from bench.baselines.amcl import likelihood_field

    cfg = AmclConfig()
    return likelihood_field(world, cfg.resolution, cfg.laser_likelihood_max_dist)


def all_methods(amcl: AmclConfig | None = None) -> list[Method]:
    """Every method of the comparison, dead reckoning first."""
    amcl_cfg = amcl or AmclConfig()
    return [
        Method("odometry", "dead reckoning", lambda w, p, s: DeadReckoning(p)),
        Method("paper", "RLuTF mode=paper", _rlutf(LocalizerConfig.paper())),
        Method("area", "RLuTF default (area)", _rlutf(LocalizerConfig(discrepancy="area"))),
        Method("turning", "RLuTF turning", _rlutf(LocalizerConfig(discrepancy="turning"))),
        Method("combined", "RLuTF combined", _rlutf(LocalizerConfig(discrepancy="combined"))),
        Method("icp", "ICP point-to-line", lambda w, p, s: PointToLineIcp(w, p), _prepare_icp),
        Method(
            "amcl",
            "AMCL likelihood field",
            lambda w, p, s: ParticleFilter(w, p, amcl_cfg, seed=s),
            _prepare_amcl,
        ),
    ]


#: The method the issue's targets are about.
DEFAULT_METHOD = "area"


@dataclass(frozen=True, eq=False)
class Trace:
    """What one method did on one run.

    Attributes:
        method: the method's name.
        poses: ``(U, 3)`` the pose after each update (NaN where none was given).
        status: ``(U,)`` the status of each update.
        seconds: ``(U,)`` wall-clock time of each update.
    """

    method: str
    poses: FloatArray
    status: tuple[str, ...]
    seconds: FloatArray


def track(
    method: Method, run: Run, seed: int = 0, on_update: Callable[[], None] | None = None
) -> Trace:
    """Run ``method`` over ``run`` and time each update.

    Args:
        method: the method.
        run: the run.
        seed: seed of the method's generator.
        on_update: called after every update (progress bars).
    """
    if method.prepare is not None:
        method.prepare(run.world)
    tracker = method.make(run.world, run.truth[0].copy(), seed)
    count = run.updates
    poses = np.full((count, 3), math.nan)
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
        status.append(est.status)
        if on_update is not None:
            on_update()
    return Trace(method.name, poses, tuple(status), seconds)
