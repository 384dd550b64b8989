"""A simulated robot's wire inputs for engine tests: odometry and scans along a trajectory."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from rlutf.map import Map as World
from rlutf.sim import LidarModel, OdometryModel, drift_odometry, make_trajectory, simulate_scan
from schemas import LaserScan, Odometry
from service.sim.wire import laser_scan

T0 = 1_732_300_000_000_000_000
STEP_NS = 100_000_000


@dataclass
class Run:
    """The truth, drifting odometry and scans of one robot, ``dt`` = 0.1 s.

    ``truth[i]`` and ``odom[i]`` hold at ``stamp(i)``; scan ``i`` is taken at ``truth[i]``.
    """

    world: World
    truth: np.ndarray
    odom: np.ndarray
    rng: np.random.Generator
    beams: int = 180

    @classmethod
    def make(cls, world: World, seed: int, steps: int, beams: int = 180) -> Run:
        rng = np.random.default_rng(seed)
        truth = make_trajectory(world, rng, steps + 1)
        return cls(world, truth, drift_odometry(truth, OdometryModel(), rng), rng, beams)

    @staticmethod
    def stamp(i: int) -> int:
        return T0 + i * STEP_NS

    @staticmethod
    def received(i: int) -> int:
        return Run.stamp(i) + 1_000_000

    def odometry(self, i: int) -> Odometry:
        o = self.odom[i]
        return Odometry(stamp_ns=self.stamp(i), x=float(o[0]), y=float(o[1]), theta=float(o[2]))

    def scan(self, i: int, at: np.ndarray | None = None) -> LaserScan:
        pose = self.truth[i] if at is None else at
        s = simulate_scan(self.world, pose, LidarModel(beams=self.beams), self.rng)
        return laser_scan(s, self.stamp(i))


def rack_beside(world: World, paths: list[np.ndarray], share: float = 0.5) -> Any:
    """A 1.2 m x 0.5 m rack (shapely box) the map lacks: clear of the walls and of every path
    by 0.7 m, within 3 m of the first path for ``share`` of its poses (seen over several
    windows)."""
    import shapely
    from shapely.geometry import box

    rng = np.random.default_rng(0)
    points = shapely.points(np.vstack([p[:, :2] for p in paths]))
    first = shapely.points(paths[0][:, :2])
    inner = world.geometry.buffer(-0.5)
    for _ in range(20000):
        p = paths[0][rng.integers(len(paths[0]))][:2] + rng.uniform(-2.5, 2.5, 2)
        rack = box(p[0] - 0.6, p[1] - 0.25, p[0] + 0.6, p[1] + 0.25)
        if (
            inner.contains(rack)
            and shapely.distance(rack, points).min() > 0.7
            and np.mean(shapely.distance(rack, first) < 3.0) > share
        ):
            return rack
    raise AssertionError("no place for a rack")
