"""Real runs from the CARMEN logs of ``bench/data/carmen`` (Intel lab, ACES building).

The map is built from the logs' corrected scans (:func:`service.maps.mapimport.build_from_carmen`,
then :func:`service.maps.mapimport.grid_to_map`, the path of ``rlutf map build``). The motion input
is the raw wheel odometry of the ``ODOM`` lines at each scan's stamp (see
:func:`raw_odometry`: the logs re-anchor it at every corrected pose, which is undone); the
reference is the corrected pose of the ``FLASER`` lines (the SLAM method's
estimate, itself off by about 1 to 3 cm). The laser sits at the robot base (the logs'
``robot_frontlaser_offset`` is 0).

Each log is also run with made-up odometry (``odometry="odom5"``, see :data:`ODOM5`): the
SLAM poses' increments with 5 % relative noise on translation and rotation (one sigma) and a
heading bias of 0.02 rad per metre, seeded. It separates what the localizers do from what
the logs' own odometry does to them.
"""

from __future__ import annotations

import gzip
import math
from functools import cache

import numpy as np

from bench.scenarios import DATA, FloatArray, IntArray, Run
from rlutf.map import Map
from rlutf.motion import compose, relative
from rlutf.scan import Scan
from rlutf.sim import OdometryModel, drift_odometry

#: The logs' no-return value is 50 m (ACES) or 81.83 m (Intel): ranges from here are no return.
RANGE_MAX = 49.9
#: Assumed one-sigma range error for the bound: the scanner's centimetre ranges plus the
#: 5 cm cells of the map built from the log. Not measured; the ratio to the bound on real
#: logs is indicative only.
SIGMA = 0.02
LOGS = ("intel", "aces")
#: The made-up odometry of the ``-odom5`` runs: 5 % relative noise per increment on
#: translation and rotation, heading bias 0.02 rad/m.
ODOM5 = OdometryModel(trans_noise=0.05, rot_noise=0.05, rot_per_metre=0.0, heading_bias=0.02)
#: Seed of the made-up odometry.
ODOM5_SEED = 5
#: The real runs: name -> (log, odometry kind).
REAL_RUNS = {
    "intel": ("intel", "log"),
    "intel-odom5": ("intel", "odom5"),
    "aces": ("aces", "log"),
    "aces-odom5": ("aces", "odom5"),
}
#: Epoch the logs' stamps (seconds since the logger started) are shifted to, ns.
BASE_NS = 1_600_000_000_000_000_000


@cache
def carmen_world(name: str) -> Map:
    """The map built from a log's corrected scans (5 cm cells, largest free component)."""
    from service.maps.mapimport import BUILT_SURFACE_CELLS, build_from_carmen, grid_to_map

    grid = build_from_carmen(DATA / "carmen" / f"{name}-corrected.log.gz")
    offset = BUILT_SURFACE_CELLS * grid.resolution  # as rlutf map build does
    return Map.from_geojson(grid_to_map(grid, map_id=name, surface_offset=offset).map["geometry"])


def raw_odometry(text: str) -> tuple[FloatArray, IntArray]:
    """The wheel odometry of a corrected CARMEN log as one continuous stream.

    In these logs every ``FLASER`` line is followed by an ``ODOM`` line with timestamp 0 that
    re-anchors the odometry at the scan's corrected pose; the readings after it continue from
    there. Chaining the increments between readings and skipping the re-anchoring jumps gives
    the robot's own dead reckoning, with no trace of the corrected poses.

    Args:
        text: the log's text.

    Returns:
        ``(M, 4)`` readings ``(timestamp s, x, y, theta)`` in file order, and ``(S,)`` for each
        ``FLASER`` line the index of the last reading before it (its stamp is the scan's).
    """
    rows: list[list[float]] = []
    before: list[int] = []
    for line in text.splitlines():
        fields = line.split(maxsplit=8)
        if not fields:
            continue
        if fields[0] == "ODOM":
            rows.append([float(fields[7]), float(fields[1]), float(fields[2]), float(fields[3])])
        elif fields[0] == "FLASER":
            before.append(len(rows) - 1)
    readings = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    out = np.empty_like(readings)
    pose = np.zeros(3)
    previous = readings[0, 1:] if len(readings) else pose
    for i, (stamp, *value) in enumerate(readings):
        current = np.asarray(value)
        if stamp != 0.0:
            pose = compose(pose, relative(previous, current))
        previous = current
        out[i, 0] = stamp
        out[i, 1:] = pose
    return out, np.maximum(np.asarray(before, dtype=np.int64), 0)


def slam_odometry(
    truth: FloatArray, model: OdometryModel = ODOM5, seed: int = ODOM5_SEED
) -> FloatArray:
    """Odometry made from the reference poses' increments with ``model``'s noise and bias."""
    return drift_odometry(truth, model, np.random.default_rng([seed, 2]))


def carmen_run(
    name: str, limit: int | None = None, odometry: str = "log", world: Map | None = None
) -> Run:
    """A real run from ``bench/data/carmen/{name}-corrected.log.gz``.

    Args:
        name: ``"intel"`` or ``"aces"``.
        limit: keep only the first ``limit`` scans (quick runs).
        odometry: ``"log"`` (the log's wheel odometry) or ``"odom5"`` (:func:`slam_odometry`);
            the run's scenario is ``name`` or ``f"{name}-odom5"``.
        world: the map (default: :func:`carmen_world`, built from all the log's scans).

    Returns:
        The run. ``odometry`` holds the raw odometry at each scan: the reading logged just
        before the scan, which carries the scan's stamp. (The readings between scans are not
        kept: their stamps jitter back by up to half a second, and the motion between two
        scans is all the localizers use.)
    """
    from service.maps.mapimport import parse_carmen

    raw = (DATA / "carmen" / f"{name}-corrected.log.gz").read_bytes()
    text = gzip.decompress(raw).decode("utf-8", errors="replace")
    log = parse_carmen(text)
    stream, at_scan = raw_odometry(text)
    count = len(log.scans) if limit is None else min(limit, len(log.scans))
    scans = tuple(
        Scan.create(
            np.where(s.ranges >= RANGE_MAX, np.nan, s.ranges),
            float(s.angles[0]),
            float(s.angles[1] - s.angles[0]),
            0.0,
            RANGE_MAX,
        )
        for s in log.scans[:count]
    )
    # CARMEN stamps are seconds since the logger started; shift them to a plausible epoch.
    stamps_ns = BASE_NS + np.round(log.stamps[:count] * 1e9).astype(np.int64)
    truth = log.poses[:count].copy()
    truth[:, 2] = (truth[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
    if odometry == "log":
        odom = stream[at_scan[:count], 1:].copy()
    elif odometry == "odom5":
        odom = slam_odometry(truth)
    else:
        raise ValueError(f"odometry: 'log' or 'odom5', got {odometry!r}")
    return Run(
        name if odometry == "log" else f"{name}-{odometry}",
        0,
        name,
        carmen_world(name) if world is None else world,
        stamps_ns,
        truth,
        odom,
        scans,
        SIGMA,
    )
