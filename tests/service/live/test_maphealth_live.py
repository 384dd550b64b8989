"""Map health of a live service: put on its key when it changes, answered to a get, via CLI."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from service_harness import Bench, Collector, SimRobot, running_bench
from shapely.geometry import shape
from sim_inputs import rack_beside

from rlutf.map import Map as World
from rlutf.sim import LidarModel, make_trajectory, simulate_scan
from service.cli.main import main
from service.sim.plan import RobotPlan

pytestmark = pytest.mark.integration

STEPS = 300  # 30 s of scan stamps: a change must persist 20 s over three 5 s windows
MORE = 200  # steps driven on while waiting: evidence is handed on with the next batches


def _near(health: dict, rack) -> bool:
    return any(
        c["kind"] == "added" and shape(c["geometry"]).distance(rack) <= 0.3
        for c in health["changes"]
    )


@pytest.fixture(params=[0, 1], ids=["threads", "worker-process"])
def served(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Bench]:
    with running_bench(tmp_path, workers=request.param) as b:
        yield b


def test_a_rack_the_map_lacks_is_put_answered_and_shown(
    served: Bench, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    bench = served
    workers = bench.service.settings.workers != 0
    built_here: list[str] = []
    if workers:
        # With worker processes this process never decodes nor validates a map over
        # INLINE_BYTES (it held the interpreter's lock for up to 0.8 s for a 10 MB map): the
        # validating process builds the map health's map and sends it back. Spawned processes
        # do not see this patch. The test's map is small: taken as if it were not.
        bench.service.maps.checker.inline_bytes = 0
        build = World.from_geojson.__func__  # type: ignore[attr-defined]

        def counted(cls: type[World], *args: object, **kw: object) -> World:
            built_here.append("from_geojson")
            return build(cls, *args, **kw)  # type: ignore[no-any-return]

        monkeypatch.setattr(World, "from_geojson", classmethod(counted))
    puts = Collector()
    sub = bench.client.declare_subscriber("rlutf/maphealth/*", puts)
    bench.put_map()
    time.sleep(0.3)
    # slowly: the rack stays in view most of the run
    n = STEPS + MORE + 1
    paths = [make_trajectory(bench.world, np.random.default_rng(s), n, speed=0.3) for s in (1, 2)]
    rack = rack_beside(bench.world, [p[: STEPS + 1] for p in paths], 0.7)
    seen = World.from_shapely(bench.world.geometry.difference(rack))
    rng = np.random.default_rng(3)
    lidar = LidarModel(beams=180)
    robots = [
        SimRobot(
            RobotPlan(rid, p, p.copy(), tuple(simulate_scan(seen, q, lidar, rng) for q in p), p[0]),
            bench.client,
            time.time_ns(),
        )
        for rid, p in (("r1", paths[0]), ("r2", paths[1]))
    ]
    for r in robots:
        r.initial_pose("m1")
    time.sleep(0.3)
    for _ in range(STEPS):
        for r in robots:
            r.advance()
        time.sleep(0.02)
    key = "rlutf/maphealth/m1"
    for _ in range(MORE):
        if any(_near(h, rack) for h in puts.on(key)):
            break
        for r in robots:
            r.advance()
        time.sleep(0.05)
    assert any(_near(h, rack) for h in puts.on(key)), (rack, json.dumps(puts.on(key)[-1]))
    sub.undeclare()
    reports = puts.on(key)
    assert all(h["map_id"] == "m1" and h["version"] == 1 for h in reports)
    assert reports[-1]["robots"] == 2 and reports[-1]["scans"] > STEPS
    if workers:
        assert built_here == []
        loaded = bench.service.maps.get("m1")
        assert loaded is not None and loaded.world is None  # the book keeps no map here
        world = bench.service.healthfeed.engine._maps["m1"].world  # the one sent back
        assert world.geometry.equals_exact(bench.world.geometry, 0.0)
        assert np.array_equal(world.segments, bench.world.segments)
    # a get answers the current report
    (answer,) = [
        json.loads(r.ok.payload.to_bytes())
        for r in bench.client.get(key, timeout=2.0)
        if r.ok is not None
    ]
    assert _near(answer, rack) and answer["scans"] >= reports[-1]["scans"]
    # and the CLI shows it
    capsys.readouterr()
    port = bench.endpoint.rsplit(":", 1)[1]
    assert main(["map", "health", "m1", "--json", "-e", f"tcp/127.0.0.1:{port}"]) == 0
    assert _near(json.loads(capsys.readouterr().out), rack)
