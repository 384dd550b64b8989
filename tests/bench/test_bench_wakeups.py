"""bench.wakeups measures a thread's wakeup and a pose-sized put over real Zenoh sessions on
loopback, each as the thread's own CPU time per event."""

from __future__ import annotations

import argparse
import math
import re

from bench.wakeups import WAITS_S, render


def test_wakeups_measures_waits_and_puts_over_a_real_router() -> None:
    text = render(argparse.Namespace(seconds=0.05))
    rows = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 1 + len(WAITS_S) + 3, text  # header, the waits, three kinds of put
    cells = [re.split(r"\s*\|\s*", r) for r in rows[1:]]
    cpu = [float(c[2]) for c in cells]
    # A wakeup and a put each cost the thread some CPU (the kernel's per-thread accounting).
    assert all(math.isfinite(x) and x > 0 for x in cpu), text
    for c in cells[len(WAITS_S) :]:
        got, sent = (int(x) for x in c[4].split(" of "))
        assert got == sent > 0, text  # the client received every put it timed
    assert "50 puts per row" in text
