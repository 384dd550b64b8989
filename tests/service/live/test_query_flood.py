"""A flood of gets costs a bounded amount of work, however many come (real Zenoh sessions).

Two instances share the fleet's map health evidence; only one of them puts the MapHealth, and
both answer gets on ``{prefix}/maphealth/*``. Making a report walks the map's whole evidence
grid (about 16 ms for a 300 m x 300 m site), so a get may not make one each time.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from service_harness import running_bench, storeless_service

import service.maphealth
from service.live.robots import RobotView

pytestmark = pytest.mark.integration

#: Every instance's reply, not one per key.
EVERY = zenoh.ConsolidationMode.NONE


def _get(client: zenoh.Session) -> list[zenoh.Reply]:
    return list(client.get("rlutf/maphealth/m1", timeout=1.0, consolidation=EVERY))


def test_a_flood_of_map_health_gets_makes_a_report_at_most_once_a_second(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    made = [0]
    real = service.maphealth.find_changes

    def counted(grid: Any) -> Any:
        made[0] += 1
        return real(grid)

    monkeypatch.setattr(service.maphealth, "find_changes", counted)
    with running_bench(tmp_path, instance="a") as bench:
        other = storeless_service(bench, "b")
        try:
            bench.put_map()
            time.sleep(0.5)
            robots = [bench.robot(f"r{i}", i, steps=120) for i in range(4)]
            for r in robots:
                r.initial_pose("m1")
            stop = threading.Event()

            def drive() -> None:
                while not stop.is_set() and robots[0].step < 110:
                    for r in robots:
                        r.advance()
                    time.sleep(0.1)

            driver = threading.Thread(target=drive)
            driver.start()
            try:
                # both instances hold evidence once it has been handed on and shared
                end = time.monotonic() + 20
                while time.monotonic() < end:
                    got = _get(bench.client)
                    if sum(r.ok is not None for r in got) == 2:
                        break
                    time.sleep(0.2)
                else:
                    keys = [str(r.ok.key_expr) for r in got if r.ok is not None]
                    held = (bench.service.maps_held(), other.maps_held(), robots[0].step)
                    pytest.fail(f"no MapHealth answered by both instances: {keys} {held}")
                made[0] = 0
                start = time.monotonic()
                gets = 0
                while time.monotonic() - start < 3.0:
                    _get(bench.client)
                    gets += 1
                elapsed = time.monotonic() - start
            finally:
                stop.set()
                driver.join()
            # a report a second for each instance's answers and one for its put, at most
            assert gets >= 50
            assert made[0] <= 2 * 2 * (elapsed + 1), (made[0], gets)
        finally:
            other.close()


def test_a_flood_of_robots_view_gets_decodes_the_fleet_a_few_times_a_second(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each answer of ``{prefix}/service/*/robots`` decodes every pose held (about 12 us a
    robot: 0.1 s at 10,000 robots): a flood of gets may not make one each."""
    made = [0]
    real = RobotView.states

    def counted(view: RobotView) -> Any:
        made[0] += 1
        return real(view)

    monkeypatch.setattr(RobotView, "states", counted)
    with running_bench(tmp_path) as bench:
        bench.put_map()
        time.sleep(0.5)
        robots = [bench.robot(f"r{i}", i, steps=60) for i in range(3)]
        for r in robots:
            r.initial_pose("m1")
        for _ in range(5):
            for r in robots:
                r.advance()
            time.sleep(0.1)
        made[0] = 0
        start, gets = time.monotonic(), 0
        while time.monotonic() - start < 2.0:
            answers = list(bench.client.get("rlutf/service/*/robots", timeout=1.0))
            assert len(answers) == 1 and answers[0].ok is not None
            gets += 1
        elapsed = time.monotonic() - start
        assert gets >= 50
        assert made[0] <= 4 * (elapsed + 1), (made[0], gets)
