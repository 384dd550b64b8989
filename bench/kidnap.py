"""Kidnapping (:mod:`bench.relocalize`): a :class:`rlutf.Localizer` tracks a simulated robot
that is teleported mid-run while its odometry sees nothing."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from bench.reloccases import BUILDING_SIZES_KIDNAP, KIDNAP_STAY, KIDNAP_WRONG
from bench.scenarios import FloatArray
from rlutf.localizer import Localizer
from rlutf.map import Map
from rlutf.motion import compose, relative, wrap_scalar
from rlutf.sim import (
    LidarModel,
    OdometryModel,
    drift_odometry,
    make_building,
    make_trajectory,
    simulate_scan,
)


@dataclass(frozen=True, eq=False)
class KidnapRun:
    """One kidnapped run.

    Attributes:
        seed: the run's seed.
        area: free area of its building, m2.
        at: update index of the kidnap (the first scan from the new pose).
        errors: ``(T,)`` position error of each update, metres (index 0 is the start).
        heading: ``(T,)`` heading error, radians.
        statuses: ``T`` statuses (``start`` at index 0).
        relocalizing: ``(T,)`` the update belongs to a relocalization.
        recovered: scans from the kidnap (it counted as 1) until the error stays under
            ``KIDNAP_STAY`` to the end of the run; ``None`` if never.
        wrong: non-lost updates over ``KIDNAP_WRONG`` off between kidnap and recovery.
        worst_wrong: the largest error among them, metres (0 if none).
        relocalize_cpu: CPU seconds of the updates that searched or followed.
    """

    seed: int
    area: float
    at: int
    errors: FloatArray
    heading: FloatArray
    statuses: tuple[str, ...]
    relocalizing: np.ndarray
    recovered: int | None
    wrong: int
    worst_wrong: float
    relocalize_cpu: float


def kidnap_path(world: Map, seed: int, steps: int, at: int) -> tuple[FloatArray, FloatArray]:
    """``(truth, odometry)``: a path whose pose ``at`` is a teleport to a random free pose (a
    new path from there); the odometry's increment at ``at`` is the motion the robot would
    have made without the teleport, so it sees no jump (1 cm-scale drift, the default
    :class:`OdometryModel`)."""
    before = make_trajectory(world, np.random.default_rng([seed, 1]), at + 1)
    after = make_trajectory(world, np.random.default_rng([seed, 7]), steps - at)
    truth = np.vstack([before[:at], after])
    seen = truth.copy()  # the path as the wheels saw it: increments without the jump
    for i in range(1, steps):
        step = relative(truth[i - 1], truth[i]) if i != at else relative(before[at - 1], before[at])
        seen[i] = compose(seen[i - 1], step)
    odometry = drift_odometry(seen, OdometryModel(), np.random.default_rng([seed, 2]))
    return truth, odometry


def kidnap_run(seed: int, steps: int, at: int) -> KidnapRun:
    """A :class:`Localizer` (default config) on a simulated building, kidnapped at ``at``."""
    sizes = BUILDING_SIZES_KIDNAP[seed % len(BUILDING_SIZES_KIDNAP)]
    world = make_building(np.random.default_rng(seed), *sizes)
    truth, odometry = kidnap_path(world, seed, steps, at)
    scan_rng = np.random.default_rng([seed, 3])
    lidar = LidarModel()
    scans = [simulate_scan(world, truth[k], lidar, scan_rng) for k in range(steps)]
    loc = Localizer(world, truth[0], seed=seed)
    err = np.zeros(steps)
    head = np.zeros(steps)
    statuses = ["start"]
    reloc = np.zeros(steps, dtype=bool)
    cpu = 0.0
    for k in range(1, steps):
        c0 = time.process_time()
        res = loc.update(relative(odometry[k - 1], odometry[k]), scans[k])
        spent = time.process_time() - c0
        if res.relocalizing:
            cpu += spent
        err[k] = math.hypot(*(res.pose[:2] - truth[k, :2]))
        head[k] = abs(wrap_scalar(float(res.pose[2] - truth[k, 2])))
        statuses.append(res.status)
        reloc[k] = res.relocalizing
    good = (err < KIDNAP_STAY[0]) & (head < math.radians(KIDNAP_STAY[1]))
    recovered = None
    for j in range(at, steps):
        if good[j:].all():
            recovered = j - at + 1
            break
    end = steps if recovered is None else at + recovered - 1
    wrong = [
        float(err[k]) for k in range(at, end) if statuses[k] != "lost" and err[k] > KIDNAP_WRONG
    ]
    return KidnapRun(
        seed,
        float(world.geometry.area),
        at,
        err,
        head,
        tuple(statuses),
        reloc,
        recovered,
        len(wrong),
        max(wrong, default=0.0),
        cpu,
    )
