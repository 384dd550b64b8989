"""The benches' resident memory of a process tree (bench.mapload's, bench.procstat's): a child
caught between fork and exec shares its parent's pages and is not counted twice (one such
sample failed a big-map test); a grandchild counts."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from typing import Any

from bench.mapload import PeakRss, process_rss_mb, rss_mb
from bench.procstat import descendants, rss_tree_mb


def _nap() -> None:
    time.sleep(0.05)


def test_spawning_children_never_doubles_the_tree() -> None:
    ballast = bytearray(400 * 2**20)
    for i in range(0, len(ballast), 4096):
        ballast[i] = 1
    ctx = mp.get_context("spawn")
    largest_child = largest_tree = 0.0
    stop = threading.Event()

    def watch() -> None:
        nonlocal largest_child, largest_tree
        me = os.getpid()
        while not stop.is_set():
            for pid, mb in process_rss_mb(me).items():
                if pid != me:
                    largest_child = max(largest_child, mb)
            largest_tree = max(largest_tree, rss_tree_mb(me))

    watcher = threading.Thread(target=watch, daemon=True)
    with PeakRss() as rss:
        baseline = rss_mb()
        watcher.start()
        for _ in range(8):
            child = ctx.Process(target=_nap)
            child.start()
            child.join()
        stop.set()
        watcher.join()
    assert 0 < largest_child < 200, largest_child  # a spawned interpreter, not the parent
    assert rss.peak - baseline < 200, (baseline, rss.peak)
    assert largest_tree - baseline < 200, (baseline, largest_tree)
    del ballast


def _grandchild(ready: Any) -> None:
    child = mp.get_context("spawn").Process(target=time.sleep, args=(30,))
    child.start()
    ready.put(child.pid)
    child.join()


def test_a_grandchild_counts_in_the_tree() -> None:
    ctx = mp.get_context("spawn")
    ready = ctx.Queue()
    child = ctx.Process(target=_grandchild, args=(ready,))
    child.start()
    grandchild = ready.get(timeout=60)
    try:
        assert grandchild in descendants(os.getpid())
        each = process_rss_mb()
        assert {os.getpid(), child.pid, grandchild} <= set(each)
        assert rss_tree_mb(os.getpid()) > sum(each.values()) - each[grandchild] / 2
    finally:
        os.kill(grandchild, 9)
        child.join(10)
