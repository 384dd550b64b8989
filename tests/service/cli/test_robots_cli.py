"""``rlutf robots`` against a real service on loopback."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from service_harness import Bench, Collector, running_bench

from service.cli.main import main

pytestmark = pytest.mark.integration


def _two_robots(bench: Bench) -> None:
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/*/pose", col)
    bench.put_map()
    time.sleep(0.3)
    robots = [bench.robot("r2", 2), bench.robot("r1", 1)]
    for r in robots:
        r.initial_pose("m1")
    time.sleep(0.3)
    for _ in range(5):
        for r in robots:
            r.advance()
        time.sleep(0.03)
    for r in robots:
        assert col.wait_for(lambda r=r: len(col.on(f"rlutf/robots/{r.robot_id}/pose")) >= 3)
    sub.undeclare()


def test_robots_json_and_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with running_bench(tmp_path) as bench:
        _two_robots(bench)
        me = bench.service.settings.instance
        assert main(["robots", "--connect", bench.endpoint, "--json", "--timeout", "2"]) == 0
        rows = json.loads(capsys.readouterr().out)
        assert [r["robot_id"] for r in rows] == ["r1", "r2"]
        assert {r["owner"] for r in rows} == {me}
        assert all(r["map_id"] == "m1" and r["latency_ms"] > 0 for r in rows)

        assert main(["robots", "--connect", bench.endpoint, "--timeout", "2"]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert lines[0].split()[:3] == ["robot", "map", "status"]
        assert [line.split()[0] for line in lines[1:]] == ["r1", "r2"]
        assert all(line.split()[-1] == me for line in lines[1:])

        # another prefix: no instance answers
        code = main(["robots", "--connect", bench.endpoint, "--prefix", "other", "--timeout", "1"])
        assert code == 1
        assert "no instance answered" in capsys.readouterr().err
