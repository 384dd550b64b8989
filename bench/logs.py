"""Benchmark runs as MCAP input logs in the WIRE.md layout, with their ground truth.

A log written here is a valid ``rlutf replay`` input and can be played onto a live bus: its
channels are the Zenoh keys (``rlutf/maps/{map_id}``, ``rlutf/robots/{robot}/initialpose``,
``.../odom``, ``.../scan``), message encoding ``json``, schema encoding ``jsonschema`` with the
checked-in documents of ``schemas/jsonschema/`` and schema names ``rlutf.*``; ``publish_time``
is the message's ``stamp_ns`` and ``log_time`` the time the robot sent it (the stamp plus a
small transmission delay). In order: the map, odometry at the start, the initial pose (the
first reference pose), then per update the odometry at the scan's stamp and the scan. The first
scan is left out, so the service runs exactly the updates the benchmark grades.

The ground truth travels in the same file on ``/bench/robots/{robot}/truth`` (schema
``bench.Truth``, JSON, one message per update, not a Zenoh key, so replay ignores it) and in a
``.npz`` beside it (``stamps_ns``, ``truth``, ``odometry``).
"""

from __future__ import annotations

import json
import math
from importlib import resources
from pathlib import Path
from typing import IO

import numpy as np
from mcap.writer import CompressionType, Writer

from bench.scenarios import Run
from schemas import InitialPose, LaserScan, Map, Odometry, encode

ROBOT = "r1"
PREFIX = "rlutf"
TRUTH_SCHEMA = "bench.Truth"
#: Delay between a message's stamp and its sending, ns (odometry, then the scan).
ODOM_DELAY_NS = 500_000
SCAN_DELAY_NS = 1_000_000
_TRUTH_JSON_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": TRUTH_SCHEMA,
    "description": "Reference pose of the robot base in the map at a scan's stamp (benchmark).",
    "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer", "minimum": 0},
        "robot_id": {"type": "string"},
        "map_id": {"type": "string"},
        "x": {"type": "number"},
        "y": {"type": "number"},
        "theta": {"type": "number"},
    },
    "required": ["stamp_ns", "robot_id", "map_id", "x", "y", "theta"],
}


class _Log:
    """Registers schemas and channels on first use and writes messages."""

    def __init__(self, output: IO[bytes]) -> None:
        self.writer = Writer(output, compression=CompressionType.ZSTD)
        self.writer.start(profile="", library="rlutf-bench")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}

    def _schema(self, name: str) -> int:
        if name not in self._schemas:
            if name == TRUTH_SCHEMA:
                data = json.dumps(_TRUTH_JSON_SCHEMA, indent=2).encode()
            else:
                data = (
                    resources.files("schemas").joinpath("jsonschema", f"{name}.json").read_bytes()
                )
            self._schemas[name] = self.writer.register_schema(name, "jsonschema", data)
        return self._schemas[name]

    def add(self, topic: str, schema: str, payload: bytes, log_ns: int, stamp_ns: int) -> None:
        if topic not in self._channels:
            self._channels[topic] = self.writer.register_channel(
                topic, "json", self._schema(schema)
            )
        channel = self._channels[topic]
        seq = self._sequence.get(channel, 0)
        self._sequence[channel] = seq + 1
        self.writer.add_message(
            channel_id=channel, log_time=log_ns, data=payload, publish_time=stamp_ns, sequence=seq
        )


def _ranges(values: np.ndarray) -> list[float | None]:
    return [float(r) if math.isfinite(r) else None for r in values.tolist()]


def write_log(run: Run, output: IO[bytes], robot: str = ROBOT) -> int:
    """Write ``run`` as an MCAP input log to a binary stream.

    Args:
        run: the run.
        output: where to write; the caller closes it.
        robot: the robot id in the topics.

    Returns:
        Messages written.
    """
    log = _Log(output)
    robot_key = f"{PREFIX}/robots/{robot}"
    t0 = int(run.stamps_ns[0])
    world = Map.model_validate(
        {"map_id": run.map_id, "version": 1, "frame_id": "map", "geometry": run.world.to_geojson()}
    )
    log.writer.add_metadata(
        "bench.run", {"scenario": run.scenario, "seed": str(run.seed), "sigma": repr(run.sigma)}
    )
    log.add(f"{PREFIX}/maps/{run.map_id}", "rlutf.Map", encode(world), t0 - 1_000_000_000, t0)
    count = 1

    def odom(k: int) -> None:
        stamp = int(run.stamps_ns[k])
        x, y, theta = (float(v) for v in run.odometry[k])
        msg = Odometry(stamp_ns=stamp, x=x, y=y, theta=theta)
        log.add(f"{robot_key}/odom", "rlutf.Odometry", encode(msg), stamp + ODOM_DELAY_NS, stamp)

    odom(0)
    x0, y0, th0 = (float(v) for v in run.truth[0])
    start = InitialPose(stamp_ns=t0, map_id=run.map_id, x=x0, y=y0, theta=th0)
    log.add(f"{robot_key}/initialpose", "rlutf.InitialPose", encode(start), t0 + SCAN_DELAY_NS, t0)
    count += 2
    for k in range(1, len(run.scans)):
        stamp = int(run.stamps_ns[k])
        odom(k)
        s = run.scans[k]
        off = s.sensor_offset
        scan = LaserScan.model_validate(
            {
                "stamp_ns": stamp,
                "angle_min": s.angle_min,
                "angle_increment": s.angle_increment,
                "range_min": s.range_min,
                "range_max": s.range_max,
                "ranges": _ranges(s.ranges),
                "sensor_offset": {"x": off[0], "y": off[1], "theta": off[2]},
            }
        )
        log.add(f"{robot_key}/scan", "rlutf.LaserScan", encode(scan), stamp + SCAN_DELAY_NS, stamp)
        truth = {
            "stamp_ns": stamp,
            "robot_id": robot,
            "map_id": run.map_id,
            "x": float(run.truth[k, 0]),
            "y": float(run.truth[k, 1]),
            "theta": float(run.truth[k, 2]),
        }
        payload = json.dumps(truth, separators=(",", ":")).encode()
        log.add(f"/bench/robots/{robot}/truth", TRUTH_SCHEMA, payload, stamp, stamp)
        count += 3
    log.writer.finish()
    return count


def write_run_files(run: Run, directory: Path) -> Path:
    """Write ``{scenario}-{seed}.mcap`` and ``.npz`` (truth) into ``directory``; return the log."""
    directory.mkdir(parents=True, exist_ok=True)
    stem = directory / f"{run.scenario}-{run.seed}"
    path = stem.with_suffix(".mcap")
    with path.open("wb") as f:
        write_log(run, f)
    np.savez_compressed(
        stem.with_suffix(".npz"), stamps_ns=run.stamps_ns, truth=run.truth, odometry=run.odometry
    )
    return path
