"""An audit split between processes by robot gives the verdict of one process."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
from mcaplog_fixtures import simulated_inputs, write_log

from service.cli.main import main
from service.logs import split as split_module
from service.logs.audit import audit_match
from service.logs.mcapfile import Record
from service.logs.mcapread import LogFile
from service.logs.replay import REPLAYED, replay, run_config
from service.logs.split import deal, replay_split

ROBOTS = ("r1", "r2", "r3")


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A log with inputs and poses, as the live service writes one: a replay's output."""
    d = tmp_path_factory.mktemp("split")
    inputs = write_log(d / "inputs.mcap", simulated_inputs(ROBOTS, steps=12))
    replay([inputs], d / "log.mcap", foxglove=False)
    return d / "log.mcap"


def _altered(log: Path, out: Path, change: dict[str, object]) -> Path:
    """``log`` with its 7th recorded pose's fields changed."""
    with LogFile(log) as lf:
        config = lf.config()
        records = list(lf.messages())
    k = [i for i, r in enumerate(records) if r.schema_name == "rlutf.PoseEstimate"][7]
    data = {**json.loads(records[k].payload), **change}
    records[k] = Record(*records[k][:2], json.dumps(data).encode(), *records[k][3:])
    return write_log(out, records, config)


def test_the_robots_are_dealt_out_by_their_messages(log: Path) -> None:
    shares = deal([log], 2)
    assert len(shares) == 2 and set().union(*shares) == set(ROBOTS)
    assert not shares[0] & shares[1] and sorted(map(len, shares)) == [1, 2]
    assert len(deal([log], 8)) == len(ROBOTS)  # no share without a robot
    assert deal([log], 1) == [set(ROBOTS)]


@pytest.mark.parametrize("change", [{}, {"x": 1.5}, {"robot_id": "intruder"}])
def test_a_split_audit_is_the_audit_of_one_process(
    log: Path, tmp_path: Path, change: dict[str, object]
) -> None:
    """As recorded, with a pose moved, and with a pose under another robot's id (a robot no
    channel names: still audited, by the first share)."""
    path = _altered(log, tmp_path / "log.mcap", change)
    one = replay([path], keep=False)
    split = replay_split([path], run_config([path]), 2, min_messages=0)
    assert audit_match(split.match) == audit_match(one.match)
    assert (split.inputs, split.dropped, split.rejected, split.unreadable_poses) == (
        one.inputs, one.dropped, one.rejected, one.unreadable_poses
    )  # fmt: skip
    robots = [a.robot for a in audit_match(split.match)]
    assert robots == sorted({*ROBOTS, *([change["robot_id"]] if "robot_id" in change else [])})


def test_the_progress_of_a_split_audit_counts_the_runs_messages_once(log: Path) -> None:
    totals: list[int] = []
    done: list[int] = []
    replay_split(
        [log], run_config([log]), 2, progress=done.append, on_total=totals.append, min_messages=0
    )
    with LogFile(log) as lf:
        messages = lf.count(REPLAYED)
    assert totals == [messages] and sum(done) == messages


def test_a_short_run_is_not_split(log: Path) -> None:
    """Under SPLIT_MIN_MESSAGES a pool would cost more than it saves: one process, which also
    recomputes the MapHealth (a split audit does not)."""
    assert replay_split([log], run_config([log]), 2).maphealth
    assert not replay_split([log], run_config([log]), 2, min_messages=0).maphealth


def test_the_cli_splits_an_audit_and_fails_a_moved_pose(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(split_module, "SPLIT_MIN_MESSAGES", 0)
    assert main(["replay", str(log), "--quiet", "--jobs", "2"]) == 0
    assert "audit: passed" in capsys.readouterr().out
    moved = _altered(log, tmp_path / "moved.mcap", {"x": 1.5})
    assert main(["replay", str(moved), "--quiet", "--jobs", "2"]) == 1
    out = capsys.readouterr().out
    assert "audit: FAILED" in out and "FAIL" in out


def test_the_processes_of_a_split_audit_run_at_a_lower_priority() -> None:
    """An operator auditing beside a live service: the audit takes the CPU the service leaves."""
    ctx = mp.get_context("spawn")
    counters = ctx.Array("q", 1, lock=False)
    with ProcessPoolExecutor(1, ctx, initializer=split_module._start, initargs=(counters,)) as pool:
        assert pool.submit(os.nice, 0).result() == min(19, os.nice(0) + split_module.NICE)


def test_jobs_are_at_most_the_cores() -> None:
    from service.cli.runaudit import jobs
    from service.cores import usable_cores

    cores = usable_cores()
    assert jobs(argparse.Namespace(jobs=0)) == cores == jobs(argparse.Namespace(jobs=10_000))
    assert jobs(argparse.Namespace(jobs=1)) == 1
