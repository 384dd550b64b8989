"""bench.recorder: the recorder's cost per scan, with and without the Foxglove views."""

from __future__ import annotations

import tempfile
from pathlib import Path

from bench.recorder import Variant, records, run


def test_views_cost_bytes_and_nothing_is_lost() -> None:
    feed = list(records(3, 30))
    assert len(feed) == 90 and [f[1] for f in feed[:3]] == [
        "rlutf.Odometry",
        "rlutf.LaserScan",
        "rlutf.PoseEstimate",
    ]
    outcomes = []
    for variant in (Variant(False), Variant(True), Variant(False, level=3, chunk_size=4096)):
        with tempfile.TemporaryDirectory() as tmp:
            outcomes.append(run(variant, feed, 10_000.0, Path(tmp)))
    plain, views, level3 = outcomes
    assert all(o.scans == 30 and o.overflowed == 0 and o.cpu_us > 0 for o in outcomes)
    assert views.bytes_per_scan > plain.bytes_per_scan > 0 and level3.bytes_per_scan > 0
    assert "zstd level 3, chunks 4 KiB" in level3.variant.label
