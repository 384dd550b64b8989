"""HeapTrimmer gives freed heap pages back to the system, at most once per interval."""

from __future__ import annotations

import time

import pytest

from service.live.memory import HeapTrimmer


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_a_burst_of_freed_messages_leaves_the_resident_set() -> None:
    trimmer = HeapTrimmer(interval_s=0.0)
    if not trimmer.available:
        pytest.skip("this C library has no malloc_trim")
    # Scan-sized blocks (malloc's, not pymalloc's), freed but for every 64th: the survivors pin
    # the heap's top, so the free pages below them stay with the process until trimmed.
    burst = [bytes(3000) + i.to_bytes(4, "little") for i in range(60_000)]
    kept = burst[::64]
    del burst
    before = _rss_mb()
    trimmer.maybe()
    after = _rss_mb()
    assert trimmer.trims == 1
    assert before - after > 50, (before, after)
    assert len(kept) == 938


def test_trims_at_most_once_per_interval() -> None:
    trimmer = HeapTrimmer(interval_s=0.2)
    if not trimmer.available:
        pytest.skip("this C library has no malloc_trim")
    for _ in range(100):
        trimmer.maybe()
    assert trimmer.trims == 0  # the first interval has not passed
    time.sleep(0.25)
    for _ in range(100):
        trimmer.maybe()
    assert trimmer.trims == 1
