"""Occupancy grids from scans at known poses, and the CARMEN log reader."""

from __future__ import annotations

import gzip
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely
import shapely.affinity
from shapely.geometry import Polygon, box

from bench.scenarios import DATA
from rlutf.map import Map
from rlutf.raycast import cast_rays
from service.maps.mapimport import (
    BUILT_SURFACE_CELLS,
    MAX_GRID_CELLS,
    CarmenError,
    CarmenLog,
    EmptyMapError,
    GridTooLargeError,
    MapFileError,
    MapImportError,
    build_from_carmen,
    build_grid,
    carmen_angles,
    grid_to_map,
    parse_carmen,
    read_carmen,
)

CARMEN = DATA / "carmen"
ROOM = box(0.0, 0.0, 6.0, 4.0).difference(box(2.5, 1.5, 3.0, 2.0))
NO_RETURN = 81.83


def room_log(scans_without_return: int = 0, shift: float = 0.0) -> str:
    """A CARMEN log of scans in ROOM (6 x 4 m with a 0.5 m pillar), exact ranges; the room
    and the poses moved by ``shift`` metres along x and y."""
    world = Map.from_shapely(shapely.affinity.translate(ROOM, shift, shift))
    angles = carmen_angles(180)
    lines = ["# synthetic", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    spots = [(1.0, 1.0), (1.0, 3.0), (3.0, 0.8), (5.0, 1.0), (5.0, 3.0), (3.0, 3.2), (1.8, 2.0)]
    stamp = 0.0
    for x0, y0 in spots:
        x, y = x0 + shift, y0 + shift
        for theta in (0.0, 0.5 * math.pi, math.pi, -0.5 * math.pi):
            ranges = cast_rays(world, [x, y, theta], angles, 40.0)[0]
            if scans_without_return:
                ranges[:] = NO_RETURN
                scans_without_return -= 1
            ranges[:5] = NO_RETURN  # a few beams with no return in every scan
            stamp += 0.1
            lines.append(f"ODOM {x} {y} {theta} 0 0 0 {stamp:.3f} nohost {stamp:.3f}")
            text = " ".join(f"{r:.4f}" for r in ranges)
            pose = f"{x} {y} {theta}"
            lines.append(f"FLASER 180 {text} {pose} {pose} {stamp:.3f} nohost {stamp:.3f}")
    return "\n".join(lines) + "\n"


def test_carmen_angles_follow_the_spacing_rule() -> None:
    even = carmen_angles(180)
    assert even[0] == pytest.approx(-0.5 * math.pi)
    assert np.diff(even) == pytest.approx(np.full(179, math.pi / 180))
    odd = carmen_angles(361)
    assert odd[0] == pytest.approx(-0.5 * math.pi)
    assert odd[-1] == pytest.approx(0.5 * math.pi)


def test_parse_carmen_reads_scans_and_odometry() -> None:
    log = parse_carmen(room_log(), max_range=50.0)
    assert len(log.scans) == 28
    assert log.odometry.shape == (28, 4)
    first = log.scans[0]
    assert first.pose.tolist() == [1.0, 1.0, 0.0]
    assert first.max_range == 50.0
    assert first.ranges[:5].tolist() == [NO_RETURN] * 5
    assert log.stamps[:2] == pytest.approx([0.1, 0.2])
    assert log.poses.shape == (28, 3)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("FLASER 3 1.0 2.0 3.0 0 0 0\n", "line 1: FLASER with 3 beams needs 12 fields"),
        ("ODOM 0 0 0 0 0 0 1 h 1\nFLASER 1 x 0 0 0 0 0 0 1 h 1\n", "line 2: not a number"),
        ("FLASER many\n", "line 1: FLASER needs a beam count"),
        ("ODOM 1 2\n", "line 1: ODOM needs 7 fields"),
        ("PARAM a b\n# nothing else\n", "no FLASER scan"),
    ],
)
def test_parse_carmen_errors_name_the_line(text: str, words: str) -> None:
    with pytest.raises(CarmenError, match=words):
        parse_carmen(text)


def test_read_carmen_accepts_gzip_and_reports_missing_files(tmp_path: Path) -> None:
    text = room_log()
    (tmp_path / "room.log").write_text(text)
    (tmp_path / "room.log.gz").write_bytes(gzip.compress(text.encode()))
    plain = read_carmen(tmp_path / "room.log")
    packed = read_carmen(tmp_path / "room.log.gz")
    assert all(
        np.array_equal(a.ranges, b.ranges) for a, b in zip(plain.scans, packed.scans, strict=True)
    )
    with pytest.raises(MapFileError, match=r"missing\.log"):
        read_carmen(tmp_path / "missing.log")
    (tmp_path / "bad.log").write_text("FLASER 2 1 1\n")
    with pytest.raises(CarmenError, match=r"bad\.log: line 1"):
        read_carmen(tmp_path / "bad.log")


def test_a_gzip_log_cut_by_a_crash_is_read_to_where_it_stops(tmp_path: Path) -> None:
    # gzip.decompress refused such a log whole ("cannot read": Compressed file ended before the
    # end-of-stream marker), where the same log plain, cut mid-line, is read without its last
    # line; two members (cat a.gz b.gz) are read whole, and corrupt data is still refused.
    text = room_log()
    packed = gzip.compress(text.encode())
    whole = read_carmen_bytes(tmp_path, packed)
    assert whole.cut is None
    cut = read_carmen_bytes(tmp_path, packed[: len(packed) * 2 // 3])
    assert cut.cut is not None and 0 < len(cut.scans) < len(whole.scans)
    lines = text.splitlines(keepends=True)
    half = "".join(lines[: len(lines) // 2]).encode()
    members = gzip.compress(half) + gzip.compress(text.encode()[len(half) :])
    two = read_carmen_bytes(tmp_path, members)
    assert two.cut is None and len(two.scans) == len(whole.scans)
    broken = bytearray(packed)
    broken[len(broken) // 2] ^= 0xFF
    with pytest.raises(MapFileError, match="cannot read"):
        read_carmen_bytes(tmp_path, bytes(broken))


def test_a_gzip_bomb_or_an_endless_log_is_refused_within_its_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A few MB of gzip can hold gigabytes of zeros, and the whole log was inflated in memory
    (a log downloaded from anywhere, given to ``rlutf map build``): now at most the bound and
    one byte more are inflated, and a larger log, packed or plain, is refused by name."""
    from service.maps.mapimport import build

    monkeypatch.setattr(build, "MAX_CARMEN_BYTES", 1 << 20)
    text = room_log().encode()
    assert len(text) < 1 << 20
    assert read_carmen_bytes(tmp_path, gzip.compress(text)).cut is None  # under it: read
    bomb = gzip.compress(b"\0" * (64 << 20), 9)  # 64 MB of zeros in ~64 kB
    with pytest.raises(MapFileError, match=r"larger than 1,048,576 bytes"):
        read_carmen_bytes(tmp_path, bomb)
    with pytest.raises(MapFileError, match=r"larger than 1,048,576 bytes"):
        read_carmen_bytes(tmp_path, text * ((1 << 20) // len(text) + 1))


def read_carmen_bytes(tmp_path: Path, data: bytes) -> CarmenLog:
    path = tmp_path / "log.gz"
    path.write_bytes(data)
    return read_carmen(path)


def test_build_from_a_synthetic_log_recovers_the_room(tmp_path: Path) -> None:
    path = tmp_path / "room.log.gz"
    path.write_bytes(gzip.compress(room_log().encode()))
    grid = build_from_carmen(path, resolution=0.05)
    assert grid.origin[2] == 0.0
    result = grid_to_map(grid, map_id="room")
    geom = result.polygons.geometry
    assert isinstance(geom, Polygon)
    # The free space ends at the cells the walls were hit in: within two cells of the walls.
    assert shapely.hausdorff_distance(geom.exterior, ROOM.exterior) <= 0.1
    assert geom.symmetric_difference(ROOM).area < 0.05 * ROOM.area
    assert len(geom.interiors) == 1
    assert shapely.hausdorff_distance(geom.interiors[0], ROOM.interiors[0]) <= 0.1
    assert not geom.contains(shapely.Point(2.75, 1.75))
    assert grid.occupied.any()
    # Seen cells carry hit ratios in percent; unseen cells are -1.
    assert set(np.unique(grid.data)) <= set(range(-1, 101))


def test_no_return_beams_mark_nothing() -> None:
    log = parse_carmen(room_log(scans_without_return=27), max_range=50.0)
    grid = build_grid(log.scans, resolution=0.05)
    only = build_grid([log.scans[27]], resolution=0.05)
    assert grid.origin == only.origin
    assert np.array_equal(grid.data, only.data)
    with pytest.raises(EmptyMapError, match="no beam with a return"):
        build_grid(log.scans[:27])


def test_build_grid_takes_any_iterable_of_tuples() -> None:
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    world = Map.from_shapely(box(-2.0, -1.0, 2.0, 1.0))

    def scans() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
        for x in (-1.0, 0.0, 1.0):
            pose = np.array([x, 0.0, 0.3])
            yield pose, cast_rays(world, pose, angles, 10.0)[0], angles, 10.0

    grid = build_grid(scans(), resolution=0.1)
    geom = grid_to_map(grid, map_id="corridor").polygons.geometry
    assert geom.area == pytest.approx(8.0, rel=0.1)
    for bad in ({"resolution": 0.0}, {"free_thresh": 0.9}):
        with pytest.raises(MapImportError):
            build_grid(scans(), **bad)  # type: ignore[arg-type]
    with pytest.raises(MapImportError, match="scan 0"):
        build_grid([(np.zeros(2), np.ones(3), np.ones(3), 5.0)])


def test_a_log_is_counted_in_chunks_read_twice_and_gives_the_same_grid() -> None:
    """A long mapping run is built in the memory of a chunk of beams: the scans are read once
    for the extent and once for the cells, and the counts add up to the grid of one chunk."""
    log = read_carmen(CARMEN / "intel-corrected.log.gz")
    scans = log.scans[:400]
    whole = build_grid(scans, chunk_beams=10**9)
    reads = []

    def again() -> Iterator[Any]:
        reads.append(1)
        return iter(scans)

    for chunked in (build_grid(scans, chunk_beams=1), build_grid(again, chunk_beams=5_000)):
        assert chunked.origin == whole.origin and chunked.data.shape == whole.data.shape
        assert (chunked.data == whole.data).all() and (chunked.free == whole.free).all()
        assert (chunked.occupied == whole.occupied).all()
    assert len(reads) == 2  # read again, not held


@pytest.mark.parametrize(("name", "area"), [("intel", (450.0, 600.0)), ("aces", (700.0, 900.0))])
def test_build_real_logs(name: str, area: tuple[float, float]) -> None:
    start = time.perf_counter()
    path = CARMEN / f"{name}-corrected.log.gz"
    result = grid_to_map(build_from_carmen(path), map_id=name)
    assert time.perf_counter() - start < 20.0
    geom = result.polygons.geometry
    assert area[0] < geom.area < area[1]
    # The robot drove in the free space: its logged poses are inside the map.
    poses = read_carmen(path).poses
    inside = Map.from_geojson(result.map["geometry"]).contains(poses[:, :2])
    assert inside.mean() > 0.98


def test_surface_offset_puts_the_walls_where_the_scanner_saw_them(tmp_path: Path) -> None:
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    short, fixed = [], []
    # Walls at several depths inside their cells (a wall on a cell edge is a special case).
    for shift in (0.005, 0.015, 0.025, 0.035, 0.045):
        path = tmp_path / f"room-{shift}.log.gz"
        path.write_bytes(gzip.compress(room_log(shift=shift).encode()))
        grid = build_from_carmen(path, resolution=0.05)
        edges = Map.from_geojson(grid_to_map(grid, map_id="room").map["geometry"])
        offset = BUILT_SURFACE_CELLS * grid.resolution
        built = Map.from_geojson(
            grid_to_map(grid, map_id="room", surface_offset=offset).map["geometry"]
        )
        truth = Map.from_shapely(shapely.affinity.translate(ROOM, shift, shift))
        for x, y, th in ([1.5, 1.2, 0.2], [4.2, 2.8, -1.0], [1.2, 3.1, 2.0]):
            pose = [x + shift, y + shift, th]
            want = cast_rays(truth, pose, angles, 20.0)[0]
            short.append(np.median(want - cast_rays(edges, pose, angles, 20.0)[0]))
            fixed.append(np.median(want - cast_rays(built, pose, angles, 20.0)[0]))
        # The pillar is still there.
        assert not built.contains_point(2.75 + shift, 1.75 + shift)
    # Traced at the cell edges, cast ranges are short by about half a cell on average; with
    # the offset, by a fraction of one.
    assert np.mean(short) > 0.35 * 0.05
    assert abs(np.mean(fixed)) < 0.15 * 0.05
    with pytest.raises(MapImportError, match="surface_offset"):
        grid_to_map(grid, map_id="room", surface_offset=0.5 * grid.resolution)


def test_surface_offset_keeps_a_wall_one_cell_thick() -> None:
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    # Two rooms split by a wall 5 cm thick (one cell at 5 cm), with no door.
    left, right = box(0.0, 0.0, 2.0, 2.0), box(2.05, 0.0, 4.05, 2.0)
    world = Map.from_shapely(shapely.MultiPolygon([left, right]))
    scans = [
        (np.array([x, 1.0, 0.0]), cast_rays(world, [x, 1.0, 0.0], angles, 10.0)[0], angles, 10.0)
        for x in (0.5, 1.5, 2.6, 3.5)
    ]
    grid = build_grid(scans, resolution=0.05)
    built = grid_to_map(
        grid, map_id="split", surface_offset=BUILT_SURFACE_CELLS * 0.05, component="all"
    )
    geom = Map.from_geojson(built.map["geometry"]).geometry
    assert isinstance(geom, shapely.MultiPolygon) and len(geom.geoms) == 2


def test_a_grid_too_large_is_refused_before_it_is_allocated() -> None:
    """``--resolution 0.001`` on the intel log asked for 10 GB per count array (MemoryError, or
    on a large host a build that takes it all): refused after the extent is read, with the
    cells, the memory and a resolution that fits."""
    log = read_carmen(CARMEN / "intel-corrected.log.gz")
    with pytest.raises(GridTooLargeError) as refused:
        build_grid(log.scans, resolution=0.001, max_cells=MAX_GRID_CELLS)
    said = str(refused.value)
    assert "1,391,435,640 cells" in said and "69.6 GB" in said
    assert f"at most {MAX_GRID_CELLS:,} cells" in said and "give --resolution 0.01 or more" in said
    # the resolution said fits, and the one just under it does not
    room = parse_carmen(room_log()).scans
    with pytest.raises(GridTooLargeError, match=r"give --resolution ([\d.]+) or more") as small:
        build_grid(room, resolution=0.05, max_cells=1000)
    fits = float(str(small.value).rsplit("--resolution ", 1)[1].split()[0])
    assert build_grid(room, resolution=fits, max_cells=1000).data.size <= 1000
    with pytest.raises(GridTooLargeError):
        build_grid(room, resolution=fits - 0.001, max_cells=1000)


def test_the_grid_limit_follows_the_memory_the_host_has() -> None:
    """A fixed 16 million cells refused a 300 m warehouse at 5 cm on any host; the limit is now
    half the memory available (at 50 bytes a cell built), never under the fixed floor."""
    from service.maps.mapimport.build import BUILD_BYTES_PER_CELL, max_grid_cells

    assert max_grid_cells(None) == max_grid_cells(10**9) == MAX_GRID_CELLS  # 1 GB free: the floor
    assert max_grid_cells(100 * 10**9) == 10**9 * 50 // BUILD_BYTES_PER_CELL  # 100 GB: 1e9 cells
    room = parse_carmen(room_log()).scans
    with pytest.raises(GridTooLargeError, match="at most 16,000,000 cells"):
        build_grid(room, resolution=1e-4, max_cells=max_grid_cells(None))


def test_non_finite_ranges_are_no_return_and_a_non_finite_pose_is_refused() -> None:
    """``nan``, ``inf`` and ``1e999`` parse (as CARMEN's strtod reads them) and mark nothing, as
    a range of the sensor's maximum does (REP 117's meaning of non-finite ranges)."""
    text = room_log()
    marked = text.replace(f"{NO_RETURN:.4f}", "nan", 28).replace(f"{NO_RETURN:.4f}", "1e999", 28)
    assert marked.count(" nan ") and marked.count(" 1e999 ")
    plain, odd = parse_carmen(text), parse_carmen(marked)
    assert not np.isfinite(np.concatenate([s.ranges for s in odd.scans])).all()
    same, other = build_grid(plain.scans), build_grid(odd.scans)
    assert same.origin == other.origin and np.array_equal(same.data, other.data)
    with pytest.raises(CarmenError, match="line 2: FLASER pose x y theta is not finite: nan 0 0"):
        parse_carmen("# x\nFLASER 1 1.0 nan 0 0 0 0 0 1 h 1\n")


def test_a_last_line_cut_short_is_left_out_and_named() -> None:
    """A crashed logger leaves a log that ends mid-line: that line is left out (and said), not
    the log refused; the same line anywhere else, or ended, is refused."""
    text = room_log()
    whole = parse_carmen(text)
    assert whole.cut is None
    lines = text.splitlines()
    for cut_at in (12, 40):  # in the ODOM line, in the FLASER line
        cut = "\n".join(lines[:-1]) + "\n" + lines[-1][:cut_at]
        log = parse_carmen(cut)
        assert len(log.scans) == len(whole.scans) - 1
        assert log.cut is not None and log.cut.startswith(f"line {len(lines)}: FLASER")
        assert "cut short" in log.cut
    odom = "\n".join(lines[:-1]) + "\nODOM 1.0"
    assert parse_carmen(odom).cut == (
        f"line {len(lines)}: ODOM needs 7 fields, got 1: the last line is cut short (the log "
        "ends mid-line, as a crashed logger leaves it) and is left out"
    )
    with pytest.raises(CarmenError, match=f"line {len(lines)}: ODOM needs 7 fields"):
        parse_carmen(odom + "\n")  # ended: a malformed line, not a cut one
    with pytest.raises(CarmenError, match="line 3: ODOM needs 7 fields"):
        parse_carmen("\n".join([*lines[:2], "ODOM 1.0", *lines[2:]]))


def test_map_build_says_what_it_left_out_and_a_map_of_next_to_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli.main import main

    text = room_log()
    cut = tmp_path / "cut.log"
    cut.write_text(text + "ODOM 1.0 2.")
    assert main(["map", "build", str(cut), "--out", str(tmp_path / "cut.json")]) == 0
    err = capsys.readouterr().err
    n = len(text.splitlines()) + 1
    assert f"warning: {cut}: line {n}: ODOM needs 7 fields, got 2: the last line is cut" in err
    assert "less than 1 m2" not in err
    # scans whose beams are nearly all no return (nan here): a map is built, and said to be tiny
    ranges = ["nan"] * 178 + ["0.2", "0.2"]
    scarce = tmp_path / "scarce.log"
    scarce.write_text(f"FLASER 180 {' '.join(ranges)} 0 0 0 0 0 0 1.0 h 1.0\n")
    assert main(["map", "build", str(scarce), "--out", str(tmp_path / "s.json")]) == 0
    err = capsys.readouterr().err
    assert "warning: the map holds 0.0" in err and "less than 1 m2" in err
    assert "not finite" in err
