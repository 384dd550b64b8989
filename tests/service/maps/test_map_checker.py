"""The map validating process (issue 21): there while maps come, gone when idle; a hostile map
costs it bounded time, and its death rejects one map, not the service's next ones."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from service_harness import WORLD, drive, running_bench, wait_until

from bench.bigmap import warehouse_payload
from bench.mapload import square_map
from rlutf.map import MapLimits
from schemas import Map, encode
from service.maps.book import MapChecker, MapRejected, check_map, content_digest

LIMITS = MapLimits(max_area=100_000.0, max_vertices=2_000_000)


def _small(map_id: str = "m1", version: int = 1) -> bytes:
    return encode(Map(map_id=map_id, version=version, geometry=WORLD.to_geojson()))


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # a child that ended but was not reaped yet is a zombie
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0] == "Z"


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_the_validating_process_ends_when_idle_and_comes_back_for_the_next_map() -> None:
    checker = MapChecker(1 << 26, LIMITS, isolated=True, idle_s=1.0)
    try:
        checker.start()
        first = checker.process.pid
        assert first is not None
        payload = _small()
        checked = checker.check("m1", payload)
        assert checked.version == 1 and checked.world is None
        assert checked.digest == content_digest(Map.model_validate_json(payload))
        assert wait_until(lambda: _gone(first), 5.0), "the idle validating process still runs"
        assert checker.process.pid is None
        # the next map starts a process again, and is validated the same way
        again = checker.check("m1", _small(version=2))
        assert again.version == 2
        assert checker.process.pid not in (None, first)
        assert checker.process.started == 2
    finally:
        checker.close()
    assert checker.process.pid is None


def test_a_process_in_use_is_not_ended() -> None:
    checker = MapChecker(1 << 26, LIMITS, isolated=True, idle_s=1.5)
    try:
        checker.start()
        pid = checker.process.pid
        for version in range(1, 5):  # a map every 0.5 s: never idle for 1.5 s
            assert checker.check("m1", _small(version=version)).version == version
            time.sleep(0.5)
        assert checker.process.pid == pid
    finally:
        checker.close()


def test_hostile_maps_are_refused_by_the_validating_process() -> None:
    checker = MapChecker(1 << 20, LIMITS, isolated=True)
    try:
        with pytest.raises(MapRejected, match="max_map_area"):
            checker.check("square", square_map("square", 2000.0))
        with pytest.raises(MapRejected, match="payload too large"):
            checker.check("big", b" " * (2 << 20))
        with pytest.raises(MapRejected, match="map_id"):
            checker.check("other", _small("m1"))
        assert checker.check("m1", _small()).version == 1
        assert checker.process.started == 1
    finally:
        checker.close()


def test_a_map_that_takes_too_long_is_rejected_and_its_process_stopped() -> None:
    payload, _ = warehouse_payload(4.0)  # about 0.6 s to validate on a free core
    checker = MapChecker(1 << 26, None, isolated=True, timeout_s=0.1)
    try:
        checker.start()
        pid = checker.process.pid
        assert pid is not None
        t0 = time.monotonic()
        with pytest.raises(MapRejected, match=r"longer than 0\.1 s"):
            checker.check("warehouse", payload)
        assert time.monotonic() - t0 < 10.0
        assert _gone(pid)
        assert checker.check("m1", _small()).version == 1  # a new process
        assert checker.process.started == 2
    finally:
        checker.close()


def test_a_killed_validating_process_rejects_its_map_only() -> None:
    payload, _ = warehouse_payload(8.0)  # about 1.2 s to validate on a free core
    checker = MapChecker(1 << 26, None, isolated=True)
    errors: list[Exception] = []

    def check() -> None:
        try:
            checker.check("warehouse", payload)
        except MapRejected as err:
            errors.append(err)

    try:
        checker.start()
        pid = checker.process.pid
        assert pid is not None
        busy = _cpu_s(pid) + 0.1
        thread = threading.Thread(target=check)
        thread.start()
        # killed while it decodes the map (its CPU time grows)
        assert wait_until(lambda: _cpu_s(pid) > busy, 20.0)
        os.kill(pid, signal.SIGKILL)
        thread.join(30.0)
        assert len(errors) == 1 and "died" in str(errors[0]), errors
        assert checker.check("m1", _small()).version == 1
        assert checker.process.pid not in (None, pid)
    finally:
        checker.close()


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        line = next(x for x in f if x.startswith("VmRSS:"))
    return int(line.split()[1]) / 1024


def test_a_map_checked_apart_comes_back_as_the_one_checked_here() -> None:
    payload, _ = warehouse_payload(0.5)
    checker = MapChecker(1 << 26, LIMITS, isolated=True, keep_world=True)
    try:
        checked = checker.check("warehouse", payload)
        assert checker.process.pid not in (None, os.getpid())
    finally:
        checker.close()
    here = check_map(payload, expected_id="warehouse", max_bytes=1 << 26, limits=LIMITS)
    assert (checked.version, checked.digest) == (here.version, here.digest)
    assert checked.world is not None and here.world is not None
    assert checked.world.geometry.equals_exact(here.world.geometry, 0.0)
    assert np.array_equal(checked.world.segments, here.world.segments)
    assert np.array_equal(checked.world.index.cell_walls, here.world.index.cell_walls)


def test_the_validating_process_gives_back_what_a_big_map_took() -> None:
    payload, _ = warehouse_payload(5.0)  # decoded and built: well over 100 MB
    checker = MapChecker(1 << 26, LIMITS, isolated=True)
    try:
        checker.start()
        pid = checker.process.pid
        assert pid is not None
        idle = _rss_mb(pid)
        assert checker.check("warehouse", payload).version == 1
        # collected and its heap trimmed once it answered, not when it ends idle
        assert wait_until(lambda: _rss_mb(pid) < idle + 30, 10.0), (idle, _rss_mb(pid))
        assert checker.process.pid == pid
    finally:
        checker.close()


def test_a_service_whose_robots_run_on_its_input_thread_checks_maps_apart(tmp_path: Path) -> None:
    # each process of the default layout (`rlutf serve --processes N`) takes its inputs and
    # runs its robots on one thread (intake "loop"); a map's check would stall them there
    with running_bench(tmp_path, intake="loop") as bench:
        checker = bench.service.maps.checker
        assert checker.isolated and checker.keep_world
        last = drive(bench, ["r1"], 30)["r1"]
        loaded = bench.service.maps.get("m1")
        assert loaded is not None and loaded.world is not None
        assert checker.process.started == 0  # m1, 2 kB, is checked in the process itself
        payload, _ = warehouse_payload(0.2)  # over INLINE_BYTES
        bench.client.put("rlutf/maps/warehouse", payload)
        assert wait_until(lambda: bench.service.maps.get("warehouse") is not None, 30.0)
        big = bench.service.maps.get("warehouse")
        assert big is not None and big.world is not None  # sent back, for its robots
        assert checker.process.pid not in (None, os.getpid())
    assert last["map_id"] == "m1" and last["status"] != "lost"
    with running_bench(tmp_path / "threads") as bench:  # callback intake, threads: the tests'
        assert not bench.service.maps.checker.isolated


def test_a_small_map_is_validated_here_and_starts_no_process() -> None:
    payload = _small()
    checker = MapChecker(1 << 26, LIMITS, isolated=True, inline_bytes=len(payload))
    try:
        checked = checker.check("m1", payload)
        assert checked.version == 1 and checked.world is None  # as from the process
        assert checker.build("m1", payload).bounds == WORLD.bounds
        with pytest.raises(MapRejected, match="max_map_area"):
            checker.check("square", square_map("square", 2000.0))
        assert checker.process.started == 0 and checker.process.pid is None
        bigger = _small(version=2) + b" "  # one byte over: validated apart
        assert checker.check("m1", bigger).version == 2
        assert checker.process.started == 1
    finally:
        checker.close()
