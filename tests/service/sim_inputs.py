"""A simulated robot's wire inputs for engine tests: odometry and scans along a trajectory."""

from __future__ import annotations

from dataclasses import dataclass

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
