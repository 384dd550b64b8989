"""bench.mapload's resident memory of a process tree: a child caught between fork and exec
shares its parent's pages and is not counted twice (one such sample failed a big-map test)."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time

from bench.mapload import PeakRss, process_rss_mb, rss_mb


def _nap() -> None:
    time.sleep(0.05)


def test_spawning_children_never_doubles_the_tree() -> None:
    ballast = bytearray(400 * 2**20)
    for i in range(0, len(ballast), 4096):
        ballast[i] = 1
    ctx = mp.get_context("spawn")
    largest_child = 0.0
    stop = threading.Event()

    def watch() -> None:
        nonlocal largest_child
        me = os.getpid()
        while not stop.is_set():
            for pid, mb in process_rss_mb(me).items():
                if pid != me:
                    largest_child = max(largest_child, mb)

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
    del ballast
