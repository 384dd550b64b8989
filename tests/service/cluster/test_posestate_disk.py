"""The pose state on a disk that stops taking writes: said on the bus when it starts and ends.

Before, a state folder on a full or read-only volume (or gone, or replaced) was one warning line
in the service's log (then one every 60 failed writes) and a health counter: ``rlutf events``
showed nothing, and nothing said when the writes worked again, unlike the recorder's
``recording_failed`` and ``recording_resumed``.
"""

from __future__ import annotations

import itertools
import json
import shutil
import time
from pathlib import Path

from service_harness import Bench, Collector, running_bench

from schemas import PoseEstimate, encode
from service.cluster.posestate import FILE_NAME, PoseState

S = 1_000_000_000


def _pose(robot: str, stamp: int) -> bytes:
    return encode(
        PoseEstimate(
            stamp_ns=stamp,
            robot_id=robot,
            map_id="m1",
            x=1.0,
            y=2.0,
            theta=0.3,
            status="tracking",
            discrepancy=0.01,
            iterations=1,
            covariance=[1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5],
        )
    )


def _break(folder: Path) -> Path:
    """The folder moved aside and a file in its place: every write fails with an OS error."""
    aside = folder.with_name(folder.name + "-aside")
    folder.rename(aside)
    folder.write_text("not a folder")
    return aside


def _mend(folder: Path, aside: Path) -> None:
    folder.unlink()
    aside.rename(folder)


def test_one_event_when_writes_start_failing_and_one_when_they_work_again(
    tmp_path: Path,
) -> None:
    said: list[tuple[str, str, str]] = []
    clock = itertools.count(10 * S, S)
    folder = tmp_path / "state"
    state = PoseState(folder, "i1", 3600.0, lambda: next(clock), report=lambda *e: said.append(e))
    state.open()
    state.pose("r1", _pose("r1", S), S, S)
    assert state.write()
    aside = _break(folder)
    for i in range(3):  # three intervals on a broken disk: one Event, not three
        state.pose("r1", _pose("r1", (2 + i) * S), (2 + i) * S, (2 + i) * S)
        assert not state.write()
    assert [(level, code) for level, code, _ in said] == [("error", "state_write_failed")]
    assert str(folder / FILE_NAME) in said[0][2] and "not kept for a restart" in said[0][2]
    _mend(folder, aside)
    assert state.write()
    assert [code for _, code, _ in said] == ["state_write_failed", "state_write_resumed"]
    assert "after" in said[1][2] and "3 failed writes" in said[1][2]
    stored = json.loads((folder / FILE_NAME).read_bytes())["robots"]["r1"]["pose"]
    assert stored["stamp_ns"] == 4 * S  # nothing kept back: the newest pose is written
    state.close()


def _events(bench: Bench) -> Collector:
    got = Collector()
    bench.client.declare_subscriber("rlutf/events", got)
    return got


def test_the_running_service_says_it_on_its_events(tmp_path: Path) -> None:
    with running_bench(tmp_path, state_interval_s=0.05) as bench:
        got = _events(bench)
        bench.put_map()
        robot = bench.robot("r1", seed=1)
        time.sleep(0.3)  # the map loaded
        robot.initial_pose("m1")
        state = tmp_path / "store" / "state"
        for _ in range(5):  # a pose, written
            robot.advance()
            time.sleep(0.1)
        assert (state / FILE_NAME).exists()
        aside = _break(state)
        codes = lambda: [e["code"] for e in got.on("rlutf/events")]  # noqa: E731
        try:
            for _ in range(30):
                robot.advance()
                time.sleep(0.1)
                if "state_write_failed" in codes():
                    break
            assert "state_write_failed" in codes()
        finally:
            _mend(state, aside)
        for _ in range(30):
            robot.advance()
            time.sleep(0.1)
            if "state_write_resumed" in codes():
                break
        assert codes().count("state_write_failed") == 1
        assert "state_write_resumed" in codes()
    shutil.rmtree(tmp_path / "store", ignore_errors=True)


def test_a_folder_gone_is_a_failed_write_not_a_new_folder(tmp_path: Path) -> None:
    """The folder is made at open only: a volume unmounted under a running service must not
    get a new state folder on the disk beneath its mount point (the writer made it again at
    each write before)."""
    said: list[tuple[str, str, str]] = []
    clock = itertools.count(10 * S, S)
    folder = tmp_path / "volume" / "state"
    state = PoseState(folder, "i1", 3600.0, lambda: next(clock), report=lambda *e: said.append(e))
    state.open()
    state.pose("r1", _pose("r1", S), S, S)
    assert state.write() and not state.figures()["state_write_failing"]
    shutil.rmtree(folder)
    state.pose("r1", _pose("r1", 2 * S), 2 * S, 2 * S)
    assert not state.write()
    assert not folder.exists()
    assert [code for _, code, _ in said] == ["state_write_failed"]
    assert state.figures()["state_write_failing"] is True
    folder.mkdir()  # the volume back
    assert state.write()
    assert state.figures()["state_write_failing"] is False
    assert state.figures()["state_write_errors"] == 1
    state.close()
