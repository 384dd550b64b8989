"""``rlutf map build LOG.mcap``: a map from a replayed log's scans and poses."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcaplog_fixtures import WORLD, simulated_inputs, write_log

from service.cli.main import main
from service.logs.mcapmaps import scans_with_poses
from service.logs.replay import replay
from service.maps.mapimport import build_grid, grid_to_map


def test_map_built_from_a_replayed_log_matches_the_world(tmp_path: Path) -> None:
    log = tmp_path / "in.mcap"
    write_log(log, simulated_inputs(robots=("r1", "r2", "r3"), steps=40, beams=360))
    out = tmp_path / "out.mcap"
    replay([log], out)
    scans = list(scans_with_poses(out))
    assert len(scans) >= 100
    result = grid_to_map(build_grid(scans, resolution=0.1), map_id="built")
    from shapely.geometry import shape

    built = shape(result.map["geometry"])
    # Only what the robots saw is free; all of it lies in the true free space.
    seen = built.area
    assert seen > 20.0
    assert built.difference(WORLD.geometry.buffer(0.2)).area < 0.05 * seen


def test_log_without_poses_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "inputs.mcap"
    write_log(log, simulated_inputs(steps=3))
    assert main(["map", "build", str(log), "--out", str(tmp_path / "m.json")]) == 1
    assert "no scan has a pose" in capsys.readouterr().err
