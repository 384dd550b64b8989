"""The dispatcher's assignment of robots to shards, and the service processes' settings."""

from __future__ import annotations

import gc
import os
import time

from rlutf.localizer import LocalizerConfig
from schemas import LaserScan, Odometry
from service.keys import Keys
from service.live.dispatch import Dispatcher
from service.live.shards import ODOM_ALONE as _ODOM_ALONE
from service.live.worker import _GC_THRESHOLDS, tune_gc


def test_tune_gc_freezes_what_is_alive_and_collects_less_often() -> None:
    before = gc.get_threshold()
    try:
        # Python's default (a test that ran `rlutf serve` in this process left it tuned)
        gc.set_threshold(700, 10, 10)
        survivor = [[i] for i in range(100)]
        tune_gc()
        assert gc.get_threshold() == _GC_THRESHOLDS
        assert _GC_THRESHOLDS[0] > 700
        assert gc.get_freeze_count() >= len(survivor)
        # frozen: in no generation that a collection walks
        walked = {id(o) for g in range(3) for o in gc.get_objects(generation=g)}
        assert id(survivor) not in walked and id(survivor[0]) not in walked
    finally:
        gc.unfreeze()
        gc.set_threshold(*before)


def test_robots_are_spread_evenly_over_worker_shards() -> None:
    """Each new robot goes to the shard with the fewest robots (not started: nothing runs)."""
    dispatcher = Dispatcher(Keys("rlutf"), LocalizerConfig(), 3, 0, lambda done: None, _no_drop)
    robots = [f"amr-{i}" for i in range(10)]
    for i, robot in enumerate(robots * 2):  # the second round: robots keep their shard
        dispatcher.submit(robot, "odom", b"{}", Odometry(stamp_ns=i, x=0, y=0, theta=0), i)
    assert sorted(s.robots for s in dispatcher.shards) == [3, 3, 4]
    # odometry alone waits for the robot's scan: nothing handed to a worker yet
    assert all(s.in_flight == 0 and not s.ready for s in dispatcher.shards)
    assert all(len(dispatcher.boxes[r].entries) == 2 for r in robots)
    for i, robot in enumerate(robots):
        dispatcher.submit(robot, "scan", b"{}", _scan(100 + i), 100 + i)
    for shard in dispatcher.shards:
        mine = {r for r in robots if dispatcher.boxes[r].shard is shard}
        # handed to the worker (in its pipe, at most max_in_flight) or waiting their turn
        sent = {r for r in mine if dispatcher.boxes[r].busy}
        assert len(sent) == min(len(mine), shard.max_in_flight) == shard.in_flight
        assert len(mine) == shard.robots and set(shard.ready) | sent == mine


def test_odometry_alone_goes_once_the_mailbox_holds_enough() -> None:
    """A robot that sends odometry and no scan does not fill its mailbox without bound."""
    dispatcher = Dispatcher(Keys("rlutf"), LocalizerConfig(), 1, 0, lambda done: None, _no_drop)
    for i in range(_ODOM_ALONE - 1):
        dispatcher.submit("r", "odom", b"{}", Odometry(stamp_ns=i, x=0, y=0, theta=0), i)
    assert dispatcher.shards[0].in_flight == 0 and dispatcher.pending() == _ODOM_ALONE - 1
    dispatcher.submit("r", "odom", b"{}", Odometry(stamp_ns=99, x=0, y=0, theta=0), 99)
    assert dispatcher.shards[0].in_flight == 1 and dispatcher.pending() == 0


def test_worker_processes_run_nicer_than_the_service_by_worker_nice() -> None:
    """Under overload the main process (inputs, counted drops) keeps the CPU it needs."""
    dispatcher = Dispatcher(
        Keys("rlutf"), LocalizerConfig(), 1, 0, lambda done: None, _no_drop, nice=3
    )
    dispatcher.start()
    try:
        pid = dispatcher.shards[0].process.pid  # type: ignore[attr-defined]
        assert pid is not None
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(mine + 3, 19)
    finally:
        dispatcher.stop()


def test_the_loop_runs_ready_batches_for_its_time_budget_then_takes_inputs_again() -> None:
    """The loop's round of updates ends on time (one batch at least), however many are ready."""
    done: list[str] = []
    dispatcher = Dispatcher(
        Keys("rlutf"), LocalizerConfig(), 0, 0, lambda d: done.append(d.robot), _no_drop,
        threads=1, loop=True,
    )  # fmt: skip
    shard = dispatcher.loop
    assert shard is not None
    robots = [f"amr-{i}" for i in range(6)]
    for i, robot in enumerate(robots):
        dispatcher.submit(robot, "scan", b"{}", _scan(100 + i), 100 + i)
    assert shard.run_ready(until=time.perf_counter()) == 1  # the budget spent: one batch
    assert shard.run_ready(until=time.perf_counter()) == 1
    assert shard.run_ready(until=time.perf_counter() + 60.0) == 4  # the rest, within budget
    assert done == robots and shard.run_ready(until=time.perf_counter() + 60.0) == 0


def _scan(stamp: int) -> LaserScan:
    return LaserScan(
        stamp_ns=stamp,
        angle_min=0.0,
        angle_increment=0.1,
        range_min=0.1,
        range_max=10.0,
        ranges=[1.0, 2.0],
    )


def _no_drop(robot: str, stamp_ns: int, received_ns: int) -> None:
    raise AssertionError("odometry is never dropped")
