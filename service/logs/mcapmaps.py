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
from typing import Any, NamedTuple, TypeVar

import numpy as np

from rlutf.motion import compose
from schemas import SCHEMA_NAMES, LaserScan, PoseEstimate, SchemaError, decode
from service.logs.mcapread import LogFile, robot_topic

ScanAtPose = tuple[np.ndarray, np.ndarray, np.ndarray, float]

_T = TypeVar("_T")
_U = TypeVar("_U")
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
    named = ", ".join(map(str, files[:3])) + (
        f" and {len(files) - 3} more" if len(files) > 3 else ""
    )
    # A scan waits for its pose (recorded a moment after it), a pose for its scan, at most
    # WAIT_NS of log time: held as they come, not the whole log (a recording of hours).
    scans: dict[tuple[str, int], tuple[int, _Scan]] = {}
    poses: dict[tuple[str, int], tuple[int, PoseEstimate]] = {}
    maps: list[str] = []
    for path in files:
        with LogFile(path) as log:
            for rec in log.messages({_SCAN, _POSE}):
                topic = robot_topic(rec.topic)
                if topic is None:
                    continue
                _forget(scans, rec.log_time_ns - WAIT_NS)
                _forget(poses, rec.log_time_ns - WAIT_NS)
                try:
                    if rec.schema_name == _SCAN:
                        scan = _Scan.of(decode(LaserScan, rec.payload))
                        key = (topic.robot, scan.stamp_ns)
                        found = _meet(poses, scans, key, rec.log_time_ns, scan)
                        if found is None:
                            continue
                        pose = found
                    else:
                        pose = decode(PoseEstimate, rec.payload)
                        if pose.status == "lost" or map_id not in (None, pose.map_id):
                            continue
                        key = (pose.robot_id, pose.stamp_ns)
                        held = _meet(scans, poses, key, rec.log_time_ns, pose)
                        if held is None:
                            continue
                        scan = held
                except SchemaError:
                    continue
                if pose.map_id not in maps:
                    maps.append(pose.map_id)
                    if len(maps) > 1:
                        raise ValueError(
                            f"{named}: the robots were localized on {len(maps)} maps "
                            f"({', '.join(sorted(maps))}): a map is built from the scans of "
                            "one; choose it with --from-map ID"
                        )
                yield scan.at(pose)
    if not maps:
        on = "" if map_id is None else f" on map {map_id!r}"
        raise ValueError(f"{named}: no scan has a pose{on} (is this a log with poses?)")


#: Log time a scan waits for its pose (or a pose for its scan), ns: a live service publishes a
#: pose within milliseconds of its scan, within seconds under load; one that never comes (the
#: scan dropped, the pose lost) must not hold the scan for the rest of the log.
WAIT_NS = 30_000_000_000


def _meet(
    others: dict[tuple[str, int], tuple[int, _T]],
    mine: dict[tuple[str, int], tuple[int, _U]],
    key: tuple[str, int],
    at_ns: int,
    item: _U,
) -> _T | None:
    """The other half waiting under ``key``, taken out; else ``item`` waits in ``mine``."""
    found = others.pop(key, None)
    if found is None:
        mine[key] = (at_ns, item)
        return None
    return found[1]


def _forget(waiting: dict[tuple[str, int], tuple[int, Any]], before_ns: int) -> None:
    """Drop what has waited since before ``before_ns`` (the oldest come first)."""
    while waiting:
        key, (since, _) = next(iter(waiting.items()))
        if since >= before_ns:
            return
        del waiting[key]


class _Scan(NamedTuple):
    """What a scan waiting for its pose keeps of its message: its ranges as an array."""

    stamp_ns: int
    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_max: float
    offset: tuple[float, float, float]

    @classmethod
    def of(cls, msg: LaserScan) -> _Scan:
        ranges = np.array([math.nan if r is None else r for r in msg.ranges])
        off = msg.sensor_offset
        return cls(
            msg.stamp_ns, ranges, msg.angle_min, msg.angle_increment, msg.range_max,
            (off.x, off.y, off.theta),
        )  # fmt: skip

    def at(self, pose: PoseEstimate) -> ScanAtPose:
        sensor = compose([pose.x, pose.y, pose.theta], list(self.offset))
        angles = self.angle_min + self.angle_increment * np.arange(len(self.ranges))
        return sensor, self.ranges, angles, self.range_max
