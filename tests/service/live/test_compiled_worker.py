"""A worker process that compiled the localizer's kernels is replaced before it gets any work.

A process that compiled keeps the compiler's memory for as long as it runs (about 130 MB more
than one that loaded the kernels from numba's cache), so on a first start after an install the
dispatcher replaces its first worker, once the cache holds the kernels, by one that loads them.
Real worker processes, a real (empty, then filled) numba cache.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from rlutf.localizer import LocalizerConfig
from service.keys import Keys
from service.live.dispatch import Dispatcher
from service.live.shards import ProcessShard


def _no_drop(robot: str, stamp_ns: int, received_ns: int) -> None:
    raise AssertionError("nothing is dropped here")


def test_a_worker_that_compiled_is_replaced_by_one_that_loads_the_kernels(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The workers' numba cache: empty, so the first worker compiles (the test process's own
    # kernels are loaded already and do not read this).
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))
    said: list[str] = []
    dispatcher = Dispatcher(Keys("rlutf"), LocalizerConfig(), 1, 0, lambda done: None, _no_drop)
    shard = dispatcher.shards[0]
    assert isinstance(shard, ProcessShard)
    first = shard.process
    dispatcher.start(said.append)
    try:
        assert first.exitcode == 0  # the compiling worker stopped when asked, not killed
        assert shard.process is not first and shard.process.is_alive()
        assert not shard.compiled  # the replacement loaded every kernel from the cache
        assert any((tmp_path / "numba").rglob("*.nbi"))
        assert said and "compiling" in said[0]  # the wait was explained, once
    finally:
        dispatcher.stop()
    # What the warm-up compiled is all a worker's robots need: their first scans (map health's
    # evidence included) compile nothing more, so none of them waits for the compiler.
    run = subprocess.run(
        [sys.executable, "-c", _ROBOTS],
        check=False,
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["loaded", "poses", "nothing-compiled"], run.stdout


#: A worker's engine on a small simulated fleet: its kernels loaded, then scans with map health.
_ROBOTS = """
from rlutf.warmup import compiled_here, warm_up
from schemas import InitialPose, LaserScan, Odometry, decode
from service.config import Settings
from service.engine import FleetEngine
from service.keys import Keys
from service.live.worker import evidence, world_of_payload
from service.sim.plan import FleetSpec, plan_fleet
from service.sim.wire import JsonWire, map_payload

print("compiled" if warm_up() else "loaded")
plan = plan_fleet(FleetSpec(robots=2, poses=12, seed=3, map_id="sim"))
wire = JsonWire(plan)
s = Settings()
engine = FleetEngine(Keys(), s.localizer, 10**9, None, evidence(True))
engine.register_map("sim", 1, world_of_payload(map_payload(plan)), 0)
poses = 0
for k in range(12):
    for i, r in enumerate(plan.robots):
        t = 10**9 + k * 10**8
        engine.handle(r.robot_id, decode(Odometry, wire.odometry(i, k, t)), t)
        start = wire.initial_pose(i, t) if k == 0 else None
        if start is not None:
            engine.handle(r.robot_id, decode(InitialPose, start), t)
        out = engine.handle(r.robot_id, decode(LaserScan, wire.scan(i, k, t)), t + 1000)
        poses += sum(o.kind == "pose" for o in out)
print("poses" if poses >= 20 else f"only {poses} poses")
print("compiled-at-a-scan" if compiled_here() else "nothing-compiled")
"""


def test_a_worker_that_loaded_the_kernels_is_kept() -> None:
    # numba's cache beside the sources holds every kernel (compiled here if it did not yet).
    warm = "from rlutf.warmup import warm_up; warm_up()"
    subprocess.run([sys.executable, "-c", warm], check=True, timeout=600)
    dispatcher = Dispatcher(Keys("rlutf"), LocalizerConfig(), 1, 0, lambda done: None, _no_drop)
    shard = dispatcher.shards[0]
    assert isinstance(shard, ProcessShard)
    first = shard.process
    dispatcher.start()
    try:
        assert shard.process is first and not shard.compiled
    finally:
        dispatcher.stop()
