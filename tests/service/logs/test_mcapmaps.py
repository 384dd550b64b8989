"""``rlutf map build LOG.mcap``: a map from a replayed log's scans and poses, or from a run's
rotated files (a folder), never from two runs or two maps mixed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcaplog_fixtures import WORLD, read_all, simulated_inputs, write_log

from service.cli.main import main
from service.logs.mcaplog import McapRecorder
from service.logs.mcapmaps import WAIT_NS, scans_with_poses
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
    assert main(["map", "build", str(log), "--out", str(tmp_path / "m.json")]) == 2
    assert "no scan has a pose" in capsys.readouterr().err


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("built")
    log = write_log(tmp / "in.mcap", simulated_inputs(robots=("r1", "r2"), steps=30, beams=180))
    replay([log], tmp / "out.mcap")
    return tmp / "out.mcap"


def _rerecord(
    source: Path,
    folder: Path,
    max_bytes: int,
    map_of: dict[str, str],
    later_ns: int = 0,
    robots: tuple[str, ...] | None = None,
    instance: str = "built",
) -> list[Path]:
    """``source``'s messages recorded again as one run (rotated at ``max_bytes``), each robot's
    poses on the map ``map_of`` names (default its own), ``later_ns`` later, only the messages
    of ``robots`` (default all) and the rest."""
    rec = McapRecorder(folder, instance=instance, max_bytes=max_bytes, chunk_size=4096)
    for r in read_all(source):
        robot = r.topic.split("/")[2] if r.topic.startswith("rlutf/robots/") else None
        if robots is not None and robot is not None and robot not in robots:
            continue
        payload = r.payload
        if r.schema_name == "rlutf.PoseEstimate":
            pose = json.loads(payload)
            pose["map_id"] = map_of.get(pose["robot_id"], pose["map_id"])
            payload = json.dumps(pose).encode()
        rec.record(r.topic, r.schema_name, payload, r.log_time_ns + later_ns, r.publish_time_ns)
    rec.close()
    return rec.files


def _built(tmp_path: Path, capsys: pytest.CaptureFixture[str], *given: str) -> tuple[int, str]:
    out = tmp_path / "m.json"
    out.unlink(missing_ok=True)
    code = main(["map", "build", *given, "--id", "b", "--resolution", "0.1", "--out", str(out)])
    err = capsys.readouterr().err
    return code, out.read_text() if code == 0 else err


def test_a_run_rotated_into_files_builds_the_map_of_the_whole_log(
    replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    files = _rerecord(replayed, tmp_path / "logs", 40_000, {})
    assert len(files) >= 3  # a scan and its pose may be in two files
    code, whole = _built(tmp_path, capsys, str(replayed))
    assert code == 0
    assert _built(tmp_path, capsys, str(tmp_path / "logs")) == (0, whole)
    assert _built(tmp_path, capsys, *map(str, reversed(files))) == (0, whole)
    # one file of the run: fewer scans, another map
    code, part = _built(tmp_path, capsys, str(files[0]))
    assert code == 0 and part != whole


def test_two_runs_or_two_maps_are_not_mixed(
    replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "logs"
    _rerecord(replayed, logs, 1 << 28, {})
    _rerecord(replayed, logs, 1 << 28, {}, later_ns=3600 * 10**9)  # a second start, later
    code, err = _built(tmp_path, capsys, str(logs))
    assert code == 2 and "the logs hold 2 recordings made at different times" in err
    (two_maps,) = _rerecord(replayed, tmp_path / "floors", 1 << 28, {"r2": "floor2"})
    code, err = _built(tmp_path, capsys, str(two_maps))
    assert code == 2 and "2 maps (floor2, m1)" in err and "--from-map" in err
    code, _ = _built(tmp_path, capsys, str(two_maps), "--from-map", "floor2")
    assert code == 0
    code, err = _built(tmp_path, capsys, str(two_maps), "--from-map", "floor3")
    assert code == 2 and "no scan has a pose on map 'floor3'" in err
    code, err = _built(tmp_path, capsys, str(tmp_path / "missing.mcap"))
    assert code == 2 and "missing.mcap: no such file" in err  # refused before any work


def test_the_runs_of_one_serves_processes_build_one_map(
    replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # rlutf serve runs one process per core, each recording its own robots as a run of its
    # own, side by side: together they are the whole log (map build refused them as two runs).
    logs = tmp_path / "logs"
    _rerecord(replayed, logs, 1 << 28, {}, robots=("r1",), instance="host-p0")
    _rerecord(replayed, logs, 1 << 28, {}, robots=("r2",), instance="host-p1")
    code, whole = _built(tmp_path, capsys, str(replayed))
    assert code == 0
    assert _built(tmp_path, capsys, str(logs)) == (0, whole)
    code, one = _built(tmp_path, capsys, str(next(logs.glob("*host-p0*"))))
    assert code == 0 and one != whole  # one process's robots alone: less of the building


def test_scans_wait_for_their_poses_a_bounded_time(replayed: Path, tmp_path: Path) -> None:
    """Pairs are made as the log is read (a recording of hours is not held): a pose recorded
    within WAIT_NS of its scan finds it, one recorded later does not (its scan was let go)."""
    records = read_all(replayed)
    all_pairs = len(list(scans_with_poses(replayed)))
    k = next(i for i, r in enumerate(records) if r.schema_name == "rlutf.PoseEstimate")
    for delay, expected in ((WAIT_NS // 2, all_pairs), (WAIT_NS + 10**9, all_pairs - 1)):
        moved = list(records)
        moved[k] = moved[k]._replace(log_time_ns=moved[k].log_time_ns + delay)
        log = write_log(tmp_path / f"moved-{delay}.mcap", moved)
        assert len(list(scans_with_poses(log))) == expected
