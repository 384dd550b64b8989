"""``rlutf robots`` against a real service on loopback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from service_harness import drive, running_bench

from service.cli.main import main

pytestmark = pytest.mark.integration


def test_robots_json_and_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with running_bench(tmp_path) as bench:
        drive(bench, ["r2", "r1"], 5)
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
        err = capsys.readouterr().err
        assert "no instance answered" in err and "access control" not in err  # no -c file
