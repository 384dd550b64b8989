"""Maps registered with the engine are built by the first input that needs them, and the
robots waiting for such a build are scheduled as long updates (off the worker's pipe thread)."""

from __future__ import annotations

import numpy as np
from shapely.geometry import box

from rlutf.localizer import LocalizerConfig
from rlutf.map import Map as World
from rlutf.sim import LidarModel, simulate_scan
from schemas import InitialPose
from service.engine import FleetEngine
from service.keys import Keys
from service.prepared import PreparedMap
from service.sim.wire import laser_scan

RNG = np.random.default_rng(4)
WORLD = World.from_shapely(box(0.0, 0.0, 10.0, 8.0).difference(box(4.0, 3.0, 5.0, 4.0)))


def test_a_map_is_built_once_by_its_first_user_and_a_robot_waiting_for_it_is_long() -> None:
    built: list[int] = []

    def source() -> World:
        built.append(1)
        return WORLD

    engine = FleetEngine(Keys("rlutf"), LocalizerConfig(), 0)
    engine.register_map("m1", 1, source, 10)
    assert built == []  # registering costs nothing
    assert engine.expects_long_update("r1", ["initialpose"])
    start = InitialPose(stamp_ns=5, map_id="m1", x=1.0, y=1.0, theta=0.0)
    engine.handle("r1", start, 20)
    assert built == [1]
    scan = simulate_scan(WORLD, np.array([1.0, 1.0, 0.0]), LidarModel(beams=90), RNG)
    engine.handle("r1", laser_scan(scan, 6), 21)  # the seeded robot's first (wide) update
    assert not engine.expects_long_update("r1", ["odom", "scan"])
    engine.register_map("m1", 2, source, 30)  # a new version, not built yet
    assert engine.expects_long_update("r1", ["odom", "scan"])
    assert engine.expects_long_update("r2", ["initialpose"])
    assert not engine.expects_long_update("r2", ["odom"])  # no map: nothing to build
    assert built == [1]


def test_a_prepared_map_has_its_index_and_field() -> None:
    prepared = PreparedMap(WORLD, LocalizerConfig())
    world = prepared.world()
    assert prepared.ready and world is WORLD
    assert {"wall_index", "distance_field"} <= set(world._derived)
    assert prepared.world() is world
