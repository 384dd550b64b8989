"""Scans with known poses from MCAP logs, for ``rlutf map build LOG.mcap`` (or a run's files).

A log in the WIRE.md layout that holds both scans and poses (a recorded run, or the output of
``rlutf replay``) pairs each scan with the PoseEstimate published for it (same robot, same
``stamp_ns``); the pose of the sensor is the robot pose composed with the scan's sensor offset.
Lost poses are left out: they are not trusted enough to draw walls with.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from rlutf.motion import compose
from schemas import SCHEMA_NAMES, LaserScan, PoseEstimate, SchemaError, decode
from service.logs.mcapread import LogFile, robot_topic

ScanAtPose = tuple[np.ndarray, np.ndarray, np.ndarray, float]

_SCAN = SCHEMA_NAMES[LaserScan]
_POSE = SCHEMA_NAMES[PoseEstimate]


def scans_with_poses(
    paths: Path | Sequence[Path], map_id: str | None = None
) -> Iterator[ScanAtPose]:
    """``(sensor pose (3,), ranges (N,), angles (N,), range_max)`` for every posed scan of the
    files ``paths`` (one run's files, as the recorder rotates them: a scan and its pose may be
    in two of them).

    Args:
        paths: the log, or the files of one run.
        map_id: only the poses on this map; ``None``: the log's poses must all be on one map.

    Raises:
        ValueError: the logs hold no scan with a pose (on ``map_id``), or poses on several maps
            and no ``map_id``.
        service.logs.mcapread.LogError: a file is not a readable MCAP log.
    """
    files = [paths] if isinstance(paths, Path) else list(paths)
    scans: dict[tuple[str, int], LaserScan] = {}
    poses: dict[tuple[str, int], PoseEstimate] = {}
    for path in files:
        with LogFile(path) as log:
            for rec in log.messages({_SCAN, _POSE}):
                topic = robot_topic(rec.topic)
                if topic is None:
                    continue
                try:
                    if rec.schema_name == _SCAN:
                        scan = decode(LaserScan, rec.payload)
                        scans[(topic.robot, scan.stamp_ns)] = scan
                    else:
                        pose = decode(PoseEstimate, rec.payload)
                        if pose.status != "lost" and map_id in (None, pose.map_id):
                            poses[(pose.robot_id, pose.stamp_ns)] = pose
                except SchemaError:
                    continue
    paired = sorted(set(scans) & set(poses), key=lambda k: (k[1], k[0]))
    named = ", ".join(map(str, files[:3])) + (
        f" and {len(files) - 3} more" if len(files) > 3 else ""
    )
    if not paired:
        on = "" if map_id is None else f" on map {map_id!r}"
        raise ValueError(f"{named}: no scan has a pose{on} (is this a log with poses?)")
    maps = sorted({poses[k].map_id for k in paired})
    if len(maps) > 1:
        raise ValueError(
            f"{named}: the robots were localized on {len(maps)} maps ({', '.join(maps)}): a "
            "map is built from the scans of one; choose it with --from-map ID"
        )
    for key in paired:
        scan, pose = scans[key], poses[key]
        off = scan.sensor_offset
        sensor = compose([pose.x, pose.y, pose.theta], [off.x, off.y, off.theta])
        ranges = np.array([math.nan if r is None else r for r in scan.ranges])
        angles = scan.angle_min + scan.angle_increment * np.arange(len(ranges))
        yield sensor, ranges, angles, scan.range_max
