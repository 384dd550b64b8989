"""Helpers for the MCAP, replay and log-tool tests: simulated runs written as logs."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import Writer as McapLibWriter

from rlutf.map import Map as World
from rlutf.sim import LidarModel, make_building, simulate_scan
from service.keys import Keys
from service.logs.mcapfile import LogWriter, Record
from service.logs.mcaplog import McapRecorder
from service.logs.mcapread import LogFile
from service.sim.plan import FleetSpec, plan_fleet
from service.sim.wire import JsonWire, fleet_records

T0 = 1_732_300_000_000_000_000
STEP_NS = 100_000_000
WORLD = make_building(np.random.default_rng(5))


def simulated_inputs(
    robots: Sequence[str] = ("r1", "r2"),
    steps: int = 20,
    seed: int = 3,
    beams: int = 120,
    prefix: str = "rlutf",
    world: World | None = None,
    seen: Callable[[list[np.ndarray]], World] | None = None,
) -> list[Record]:
    """A map (``world``, default :data:`WORLD`), initial poses (5 cm off), then odometry and a
    scan per robot per step, in log order: :mod:`service.sim`'s fleet, as its robots put it;
    with ``seen``, the scans are of the world it makes of the robots' paths (a changed world).

    ``log_time`` is strictly increasing: 1 ms after the stamp, plus 10 us per robot.
    """
    spec = FleetSpec(
        robots=len(robots),
        poses=steps + 1,
        beams=beams,
        seed=seed,
        map_id="m1",
        robot_ids=tuple(robots),
        initial_offset=(0.05, 0.0, 0.0),
    )
    plan = plan_fleet(spec, WORLD if world is None else world)
    if seen is not None:
        changed = seen([r.truth for r in plan.robots])
        rng = np.random.default_rng([seed, 99])
        lidar = LidarModel(beams=beams)
        robots = tuple(
            replace(r, scans=tuple(simulate_scan(changed, p, lidar, rng) for p in r.truth))
            for r in plan.robots
        )
        plan = replace(plan, robots=robots)
    return list(fleet_records(JsonWire(plan, Keys(prefix)), steps, T0, STEP_NS))


def record_with_poses(
    folder: Path,
    scratch: Path,
    inputs: Sequence[Record],
    tamper: Callable[[str, int, bytes], bytes] | None = None,
    **recorder: Any,
) -> McapRecorder:
    """``inputs`` and the poses the engine computes for them, recorded by the service's own
    recorder into ``folder`` as the live service records them (a pose at its scan's receive
    time); ``tamper(robot, k, payload)`` may change robot's ``k``-th pose. ``scratch`` takes
    the inputs' log the poses are computed from."""
    from service.logs.replay import replay

    computed = replay([write_log(scratch / "inputs.mcap", inputs)])
    received = {
        (r.topic.split("/")[2], r.publish_time_ns): r.log_time_ns
        for r in inputs
        if r.schema_name == "rlutf.LaserScan"
    }
    poses = []
    for robot, records in computed.recomputed.items():
        for k, p in enumerate(records):
            payload = p.payload if tamper is None else tamper(robot, k, p.payload)
            at = received[(robot, p.stamp_ns)]
            poses.append(
                Record(f"rlutf/robots/{robot}/pose", "rlutf.PoseEstimate", payload, at, p.stamp_ns)
            )
    rec = McapRecorder(folder, **recorder)
    rec.set_config(computed.config.settings)
    for r in sorted([*inputs, *poses], key=lambda r: r.log_time_ns):
        rec.record(r.topic, r.schema_name, r.payload, r.log_time_ns, r.publish_time_ns)
    rec.close()
    return rec


def add_outside_chunks(
    writer: McapLibWriter, channel: int, log_time: int, data: bytes, publish_time: int
) -> None:
    """Write a message with the ``mcap`` library's chunked writer outside any chunk, as MCAP
    allows beside indexed chunks (after the chunk in progress, which is closed first)."""
    writer.flush()
    builder = writer._Writer__chunk_builder  # type: ignore[attr-defined]
    writer._Writer__chunk_builder = None  # type: ignore[attr-defined]
    try:
        writer.add_message(channel, log_time, data, publish_time)
    finally:
        writer._Writer__chunk_builder = builder  # type: ignore[attr-defined]


def unindex_last_chunk(writer: McapLibWriter) -> None:
    """Close the ``mcap`` library writer's chunk in progress and leave it out of the file's chunk
    index, as a writer that loses track of a chunk (or a hand that removes its index) would."""
    writer.flush()
    writer._Writer__chunk_indices.pop()  # type: ignore[attr-defined]


def write_log(
    path: Path,
    records: Iterable[Record],
    config: dict[str, Any] | None = None,
    chunk_size: int = 1 << 20,
) -> Path:
    """Write records (no Foxglove views) into a complete log."""
    with open(path, "wb") as stream:
        writer = LogWriter(stream, chunk_size=chunk_size)
        if config is not None:
            writer.write_config(config)
        writer.write_all(records)
        writer.finish()
    return path


def read_all(path: Path, schema_names: Iterable[str] | None = None) -> list[Record]:
    """Every message of a log in log-time order."""
    with LogFile(path) as lf:
        return list(lf.messages(None if schema_names is None else set(schema_names)))


def payloads(path: Path, schema_name: str) -> list[bytes]:
    """Payloads of one schema in log-time order."""
    return [r.payload for r in read_all(path, [schema_name])]
