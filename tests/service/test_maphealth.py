"""Map health in the engine: evidence beside the localizer, merged in any order, reported."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest
import shapely
from shapely.geometry import shape
from sim_inputs import Run, rack_beside

from rlutf.localizer import Localizer, LocalizerConfig, LocalizeResult
from rlutf.map import Map as World
from rlutf.scan import Scan
from rlutf.sim import make_building, make_trajectory
from schemas import InitialPose, LaserScan, MapHealth, Odometry, decode
from service.engine import FleetEngine
from service.keys import Keys
from service.maphealth import MapHealthEngine, ScanEvidence

STEPS = 260  # 26 s at 10 Hz: a change must persist 20 s over three 5 s windows
KEYS = Keys()
CONFIG = LocalizerConfig()


@dataclass
class Inputs:
    start: InitialPose
    steps: list[tuple[Odometry, LaserScan, int]]  # odometry, scan, receive time


@pytest.fixture(scope="module")
def changed() -> tuple[World, shapely.Polygon, dict[str, Inputs]]:
    """The map, a rack the map lacks, and two robots' inputs in the world with the rack."""
    world = make_building(np.random.default_rng(5))
    paths = [make_trajectory(world, np.random.default_rng(s), STEPS + 1) for s in (1, 2)]
    rack = rack_beside(world, paths)
    seen = World.from_shapely(world.geometry.difference(rack))
    inputs = {}
    for robot, seed, path in (("a", 1, paths[0]), ("b", 2, paths[1])):
        run = Run.make(seen, seed, STEPS, beams=360)
        run.truth = path
        t = path[0]
        start = InitialPose(stamp_ns=run.stamp(0), map_id="m1", x=t[0], y=t[1], theta=t[2])
        steps = [(run.odometry(i), run.scan(i), run.received(i)) for i in range(STEPS + 1)]
        inputs[robot] = Inputs(start, steps)
    return world, rack, inputs


def _drive(
    engines: dict[str, FleetEngine],
    inputs: dict[str, Inputs],
    world: World,
    handover: Callable[[int], None],
) -> None:
    """Each robot's inputs to its engine, robots interleaved; ``handover(i)`` after step i."""
    for engine in {id(e): e for e in engines.values()}.values():
        engine.register_map("m1", 1, world, 0)
    for robot, inp in inputs.items():
        odom, _, received = inp.steps[0]
        engines[robot].handle(robot, odom, received)
        engines[robot].handle(robot, inp.start, received)
    for i in range(1, STEPS + 1):
        for robot, inp in inputs.items():
            odom, scan, received = inp.steps[i]
            engines[robot].handle(robot, odom, received)
            engines[robot].handle(robot, scan, received)
        handover(i)


def _health(world: World) -> MapHealthEngine:
    health = MapHealthEngine(KEYS)
    health.register_map("m1", 1, world)
    return health


def test_an_added_rack_is_reported_the_same_whoever_counted_which_scan(changed) -> None:
    world, rack, inputs = changed
    # replay: one engine for both robots
    single = ScanEvidence()
    engine = FleetEngine(KEYS, CONFIG, evidence=single)
    one = _health(world)
    _drive({"a": engine, "b": engine}, inputs, world, lambda i: one.merge(single.take()))
    # live: two workers, one robot each, handing on at other times, merged in other orders
    ev = {"a": ScanEvidence(), "b": ScanEvidence()}
    workers = {r: FleetEngine(KEYS, CONFIG, evidence=e) for r, e in ev.items()}
    two = _health(world)

    def hand(i: int) -> None:
        if i % 7 == 0:
            two.merge(ev["b"].take())
        if i % 13 == 0:
            two.merge(ev["a"].take())

    _drive(workers, inputs, world, hand)
    two.merge(ev["b"].take() + ev["a"].take())
    a, b = one.answer("m1"), two.answer("m1")
    assert a is not None and a == b
    report = decode(MapHealth, a)
    assert (report.map_id, report.version, report.robots) == ("m1", 1, 2)
    assert report.scans > 0.9 * 2 * STEPS
    assert report.since_ns == inputs["a"].steps[1][1].stamp_ns
    assert report.stamp_ns == inputs["a"].steps[-1][1].stamp_ns
    added = [c for c in report.changes if c.kind == "added"]
    assert added, report
    assert min(shape(c.geometry.model_dump()).distance(rack) for c in added) <= 0.3
    assert all(0.0 <= c.confidence <= 1.0 and c.robots >= 1 for c in report.changes)
    assert not [c for c in report.changes if c.kind == "removed"]


def test_puts_at_most_once_an_interval_only_when_changed_and_reset_by_a_new_version(
    changed,
) -> None:
    world, _, inputs = changed
    evidence = ScanEvidence()
    engine = FleetEngine(KEYS, CONFIG, evidence=evidence)
    health = _health(world)
    puts: list[tuple[int, bytes]] = []

    def hand(i: int) -> None:
        now = inputs["a"].steps[i][2]
        health.merge(evidence.take())
        puts.extend((now, out.payload) for out in health.due(now))

    _drive({"a": engine, "b": engine}, inputs, world, hand)
    assert len(puts) >= 10
    times = [t for t, _ in puts]
    assert min(np.diff(times)) >= 1_000_000_000
    assert all(a != b for (_, a), (_, b) in itertools.pairwise(puts))
    assert len(health.due(times[-1] + 10**10)) <= 1  # the evidence of the last second
    assert health.due(times[-1] + 2 * 10**10) == []  # nothing new: nothing put
    # a new version: the evidence starts afresh, the old version's grids are dropped
    late = ScanEvidence()
    assert late.observe("m1", 1, world, "a", 1, _good_result(world, inputs["a"]))
    health.register_map("m1", 2, world)
    assert health.answer("m1") is None
    health.merge(late.take())
    assert health.answer("m1") is None


def _good_result(world: World, inp: Inputs) -> LocalizeResult:
    """A localizer's result at the robot's start, from its first scan."""
    scan = inp.steps[1][1]
    start = [inp.start.x, inp.start.y, inp.start.theta]
    ranges = np.array([np.nan if r is None else r for r in scan.ranges])
    s = Scan.create(ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max)
    return Localizer(world, start).update(np.zeros(3), s)


def test_evidence_shared_over_the_bus_gives_the_same_report(changed) -> None:
    """Two instances, one robot each: each merges its own evidence and the other's as
    :mod:`service.evidence` carries it, and both hold the report one engine of both makes."""
    from service.evidence import decode_evidence, encode_evidence

    world, _, inputs = changed
    ev = {"a": ScanEvidence(), "b": ScanEvidence()}
    workers = {r: FleetEngine(KEYS, CONFIG, evidence=e) for r, e in ev.items()}
    mine = {"a": _health(world), "b": _health(world)}
    both = _health(world)

    def hand(i: int) -> None:
        if i % 10 == 0:
            for robot, other in (("a", "b"), ("b", "a")):
                handed = ev[robot].take()
                both.merge(handed)
                mine[robot].merge(handed)
                mine[other].merge(decode_evidence(encode_evidence(handed)))

    _drive(workers, inputs, world, hand)
    hand(0)
    report = both.answer("m1")
    assert report is not None and mine["a"].answer("m1") == report == mine["b"].answer("m1")
    assert decode(MapHealth, report).robots == 2
