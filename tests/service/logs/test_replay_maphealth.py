"""Replay recomputes map health from a log's scans and records it (schema rlutf.MapHealth)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import shapely
from mcaplog_fixtures import WORLD, read_all, simulated_inputs, write_log
from shapely.geometry import shape
from sim_inputs import rack_beside

from rlutf.map import Map as World
from schemas import MapHealth, decode
from service.cli.main import main
from service.logs.replay import replay

STEPS = 260


@pytest.fixture(scope="module")
def changed_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, shapely.Polygon]:
    racks: list[shapely.Polygon] = []

    def seen(paths: list[np.ndarray]) -> World:
        racks.append(rack_beside(WORLD, paths))
        return World.from_shapely(WORLD.geometry.difference(racks[0]))

    path = tmp_path_factory.mktemp("maphealth") / "in.mcap"
    write_log(path, simulated_inputs(steps=STEPS, beams=360, seen=seen))
    return path, racks[0]


def test_replay_records_map_health_and_reproduces_it(
    changed_log: tuple[Path, shapely.Polygon], tmp_path: Path
) -> None:
    log, rack = changed_log
    one = replay([log], tmp_path / "one.mcap")
    two = replay([log], tmp_path / "two.mcap")
    assert one.maphealth == two.maphealth and one.maphealth["m1"]
    records = read_all(tmp_path / "one.mcap", ["rlutf.MapHealth"])
    assert [r.payload for r in records] == one.maphealth["m1"]
    assert {r.topic for r in records} == {"rlutf/maphealth/m1"}
    times = [r.log_time_ns for r in records]
    assert all(b - a >= 1_000_000_000 for a, b in itertools.pairwise(times))
    last = decode(MapHealth, records[-1].payload)
    assert records[-1].publish_time_ns == last.stamp_ns
    assert (last.version, last.robots) == (1, 2)
    added = [c for c in last.changes if c.kind == "added"]
    assert min(shape(c.geometry.model_dump()).distance(rack) for c in added) <= 0.3


def test_nothing_changed_nothing_reported(tmp_path: Path) -> None:
    log = write_log(tmp_path / "in.mcap", simulated_inputs(steps=STEPS, beams=360))
    result = replay([log], None)
    assert result.maphealth["m1"]
    assert decode(MapHealth, result.maphealth["m1"][-1]).changes == ()


def test_the_cli_reads_the_last_map_health_of_a_log_folder(
    changed_log: tuple[Path, shapely.Polygon], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log, _ = changed_log
    folder = tmp_path / "logs"
    folder.mkdir()
    result = replay([log], folder / "replayed.mcap")
    last = json.loads(result.maphealth["m1"][-1])
    for given in ([str(folder)], [str(folder / "replayed.mcap")]):
        capsys.readouterr()
        assert main(["map", "health", "m1", "--json", "--log", *given]) == 0
        assert json.loads(capsys.readouterr().out) == last
    assert main(["map", "health", "other", "--log", str(folder)]) == 1
    assert "no MapHealth recorded in the logs for map 'other'" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.mcap").write_text("not a log")
    for bad, said in (("empty", "a folder with no log file"), ("notes.mcap", "not an MCAP")):
        assert main(["map", "health", "m1", "--log", str(tmp_path / bad)]) == 2
        assert said in capsys.readouterr().err
