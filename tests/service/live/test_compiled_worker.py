"""A worker process that compiled the localizer's kernels is replaced before it gets any work.

A process that compiled keeps the compiler's memory for as long as it runs (about 130 MB more
than one that loaded the kernels from numba's cache), so on a first start after an install the
dispatcher replaces its first worker, once the cache holds the kernels, by one that loads them.
Real worker processes, a real (empty, then filled) numba cache.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rlutf.localizer import LocalizerConfig
from service.keys import Keys
from service.live.dispatch import Dispatcher
from service.live.shards import ProcessShard


def _no_drop(robot: str, stamp_ns: int, received_ns: int) -> None:
    raise AssertionError("nothing is dropped here")


def test_a_worker_that_compiled_is_replaced_by_one_that_loads_the_kernels(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The workers' numba cache: empty, so the first worker compiles (the test process's own
    # kernels are loaded already and do not read this).
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))
    said: list[str] = []
    dispatcher = Dispatcher(Keys("rlutf"), LocalizerConfig(), 1, 0, lambda done: None, _no_drop)
    shard = dispatcher.shards[0]
    assert isinstance(shard, ProcessShard)
    first = shard.process
    dispatcher.start(said.append)
    try:
        assert first.exitcode == 0  # the compiling worker stopped when asked, not killed
        assert shard.process is not first and shard.process.is_alive()
        assert not shard.compiled  # the replacement loaded every kernel from the cache
        assert any((tmp_path / "numba").rglob("*.nbi"))
        assert said and "compiling" in said[0]  # the wait was explained, once
    finally:
        dispatcher.stop()


def test_a_worker_that_loaded_the_kernels_is_kept() -> None:
    # numba's cache beside the sources holds every kernel (compiled here if it did not yet).
    warm = "from rlutf.warmup import warm_up; warm_up()"
    subprocess.run([sys.executable, "-c", warm], check=True, timeout=600)
    dispatcher = Dispatcher(Keys("rlutf"), LocalizerConfig(), 1, 0, lambda done: None, _no_drop)
    shard = dispatcher.shards[0]
    assert isinstance(shard, ProcessShard)
    first = shard.process
    dispatcher.start()
    try:
        assert shard.process is first and not shard.compiled
    finally:
        dispatcher.stop()
