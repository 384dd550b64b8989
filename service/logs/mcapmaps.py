"""Scans with known poses from an MCAP log, for ``rlutf map build LOG.mcap``.

A log in the WIRE.md layout that holds both scans and poses (a recorded run, or the output of
``rlutf replay``) pairs each scan with the PoseEstimate published for it (same robot, same
``stamp_ns``); the pose of the sensor is the robot pose composed with the scan's sensor offset.
Lost poses are left out: they are not trusted enough to draw walls with.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from rlutf.motion import compose
from schemas import SCHEMA_NAMES, LaserScan, PoseEstimate, SchemaError, decode
from service.logs.mcapread import LogFile, robot_topic

ScanAtPose = tuple[np.ndarray, np.ndarray, np.ndarray, float]

_SCAN = SCHEMA_NAMES[LaserScan]
_POSE = SCHEMA_NAMES[PoseEstimate]


def scans_with_poses(path: Path) -> Iterator[ScanAtPose]:
    """``(sensor pose (3,), ranges (N,), angles (N,), range_max)`` for every posed scan.

    Raises:
        ValueError: the log holds no scan with a pose.
        service.logs.mcapread.LogError: the file is not a readable MCAP log.
    """
    scans: dict[tuple[str, int], LaserScan] = {}
    poses: dict[tuple[str, int], PoseEstimate] = {}
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
                    if pose.status != "lost":
                        poses[(pose.robot_id, pose.stamp_ns)] = pose
            except SchemaError:
                continue
    paired = sorted(set(scans) & set(poses), key=lambda k: (k[1], k[0]))
    if not paired:
        raise ValueError(f"{path}: no scan has a pose (is this a log with poses?)")
    for key in paired:
        scan, pose = scans[key], poses[key]
        off = scan.sensor_offset
        sensor = compose([pose.x, pose.y, pose.theta], [off.x, off.y, off.theta])
        ranges = np.array([math.nan if r is None else r for r in scan.ranges])
        angles = scan.angle_min + scan.angle_increment * np.arange(len(ranges))
        yield sensor, ranges, angles, scan.range_max
