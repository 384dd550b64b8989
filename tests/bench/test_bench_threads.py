"""Per-thread counters of ``bench.threads``: CPU, and context switches counted where they happen."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

from bench.fleet import thread_rows
from bench.threads import task_cpu, task_switches, thread_table

pytestmark = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="Linux /proc")


def test_switches_are_counted_for_the_thread_that_sleeps_and_wakes() -> None:
    pid = os.getpid()
    started, go, napped, leave = (threading.Event() for _ in range(4))

    def napper() -> None:
        started.set()
        go.wait()
        for _ in range(50):
            time.sleep(0.001)  # each sleep is a voluntary switch
        napped.set()
        leave.wait()  # alive (its /proc entry there) until counted

    t = threading.Thread(target=napper)
    t.start()
    started.wait()
    assert t.native_id is not None
    before = task_switches(pid)
    cpu_before = task_cpu(pid)
    go.set()
    napped.wait()
    after = task_switches(pid)
    leave.set()
    t.join()
    names = {t.native_id: "napper-1"}
    table = dict(thread_table(before, after, names, per=10, scale=1.0))
    # 50 sleeps, per 10 units of work: at least 5 switches a unit, under the role's name
    assert table["napper-*"] >= 5.0
    # the same snapshots' shape as task_cpu's: one entry per thread, kernel names alike (of
    # the threads still there: another test's thread may end meanwhile in this process)
    still = set(task_cpu(pid))
    assert set(after) >= (set(cpu_before) & still) - {t.native_id}
    assert all(isinstance(v, float) for _, v in after.values())


def test_the_fleet_table_puts_switches_beside_cpu() -> None:
    rows = thread_rows(
        {"host": {"rx-*": 0.041, "rlutf-inputs": 0.296, "idle": 0.001}},
        {"host": {"rx-*": 2.5, "rlutf-inputs": 1.16}},
    )
    assert rows == ["| host | rlutf-inputs | 0.296 | 1.16 |", "| host | rx-* | 0.041 | 2.50 |"]
