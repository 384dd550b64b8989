"""The pure parts of the soak benchmark: the slope fit and the verdicts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.soakplan import (
    FileCheck,
    LatencyHistogram,
    counted_verdict,
    exit_code,
    halves_per_10min,
    logs_verdicts,
    memory_by_process,
    memory_verdict,
    outcome,
    queue_grows,
    queue_verdict,
    slope_per_10min,
)


def test_slope_is_per_ten_minutes() -> None:
    t = np.arange(0, 30, 1 / 6)
    assert slope_per_10min(t, 400 + 0.05 * t) == pytest.approx(0.5)
    assert slope_per_10min(t, np.full_like(t, 400.0)) == pytest.approx(0.0)
    assert math.isnan(slope_per_10min([1.0], [2.0]))
    assert slope_per_10min([0, 1, 2, math.nan], [0, 1, 2, 3]) == pytest.approx(10.0)


def test_memory_verdict_leaves_out_the_warm_up() -> None:
    t = np.arange(0, 30, 1 / 6)
    rss = np.where(t < 5, 300 + 30 * t, 450 + 0.02 * t)  # grows while warming up, then flat
    assert memory_verdict(t, rss, warmup_minutes=5).ok
    assert not memory_verdict(t, rss, warmup_minutes=0).ok
    leak = 450 + 0.2 * t  # 2 MB per 10 minutes
    verdict = memory_verdict(t, leak, warmup_minutes=5)
    assert not verdict.ok and "+2.00 MB per 10 min" in verdict.detail
    assert "first half +2.00, second half +2.00" in verdict.detail  # a leak grows in both
    assert not verdict.hard


def test_memory_verdict_tells_a_heap_that_settles_from_a_leak() -> None:
    t = np.arange(0, 30, 1 / 6)
    settles = 450 + 4 * (1 - np.exp(-(t - 5) / 3))  # 4 MB more, reached within ten minutes
    verdict = memory_verdict(t, settles, warmup_minutes=5)
    early, late = halves_per_10min(t[t >= 5], settles[t >= 5])
    assert early > 1.0 and abs(late) < 0.2
    assert f"first half {early:+.2f}, second half {late:+.2f}" in verdict.detail
    assert all(math.isnan(x) for x in halves_per_10min([3.0], [1.0]))


def test_memory_by_process_names_the_process_and_the_part_that_grows() -> None:
    t = np.arange(0, 30, 1 / 6)
    samples = []
    for m in t:
        host_anon = 90 + (0.3 * (m - 5) if m >= 5 else 0.0)  # the host's heap grows 3 MB per 10 min
        samples.append(
            {
                "minute": float(m),
                "mem_host_rss": host_anon + 110, "mem_host_anon": host_anon,
                "mem_host_file": 110.0, "mem_host_pss": host_anon + 30,
                "mem_p1_rss": 200.0, "mem_p1_anon": 90.0, "mem_p1_file": 110.0,
                "mem_p1_pss": 125.0,
            }
        )  # fmt: skip
    lines = memory_by_process(samples, warmup_minutes=5)
    host = next(line for line in lines if line.startswith("| host |"))
    other = next(line for line in lines if line.startswith("| p1 |"))
    cells = [c.strip() for c in host.split("|")[2:-1]]
    assert cells[1] == "90 -> 97 (+3.00 per 10 min)"  # the heap
    assert cells[2] == "110 -> 110 (+0.00 per 10 min)"  # the mapped files
    assert "+0.00 per 10 min" in other and "+3.00" not in other
    assert memory_by_process([{"minute": 0.0, "rss_service_mb": 1.0}], 0.0) == []


def test_a_queue_that_creeps_up_grows_and_a_bursty_one_does_not() -> None:
    rng = np.random.default_rng(0)
    bursty = rng.integers(0, 20, 90).astype(float)
    bursty[70] = 500.0  # one busy moment late in the run
    assert not queue_grows(bursty, margin=10)
    creeping = np.arange(90, dtype=float) * 2 + rng.integers(0, 20, 90)
    assert queue_grows(creeping, margin=10)
    assert not queue_grows([0.0, 100.0], margin=0)  # too few samples for a trend


def test_queue_verdict_of_a_queue_not_reported() -> None:
    verdict = queue_verdict("recorder queue", [0.0, 1.0], [math.nan, math.nan], 0.0, 10)
    assert verdict.ok and "not reported" in verdict.detail


def test_every_scan_answered_or_counted() -> None:
    assert counted_verdict(1000, 900, 80, 20).ok
    missing = counted_verdict(1000, 900, 80, 10)
    assert not missing.ok and "10 uncounted" in missing.detail and missing.hard
    assert not counted_verdict(1000, 1000, -1, 0).ok  # no health: dropped unknown


def _file(
    name: str, messages: int = 10, poses: int = 4, error: str | None = None, sequence: int = 0
) -> FileCheck:
    return FileCheck(name, 1000, messages, messages, poses, 14.9, error, "run-a", sequence)


def test_logs_verdicts() -> None:
    files = [_file(f"f{i}.mcap", sequence=i) for i in range(4)]
    good = logs_verdicts(files, [], 60.0, 15.0, poses_published=16, recorder_overflow=0)
    assert all(v.ok and v.hard for v in good)
    few = logs_verdicts(files[:1], [], 60.0, 15.0, 4, 0)
    assert [v.ok for v in few] == [False, True, True, True, True]
    part = logs_verdicts(files, ["f4.mcap.part"], 60.0, 15.0, 16, 0)
    assert [v.ok for v in part] == [True, False, True, True, True]
    broken = [*files[:3], _file("f3.mcap", error="damaged", sequence=3)]
    assert [v.ok for v in logs_verdicts(broken, [], 60.0, 15.0, 16, 0)][2] is False
    short_read = [*files[:3], FileCheck("f3.mcap", 1000, 9, 10, 4, 14.9, None, "run-a", 3)]
    assert [v.ok for v in logs_verdicts(short_read, [], 60.0, 15.0, 16, 0)][2] is False
    # the files of one start of the service: one run, numbered from 0 in file order
    two_runs = [*files[:3], files[3]._replace(run="run-b")]
    assert not logs_verdicts(two_runs, [], 60.0, 15.0, 16, 0)[4].ok
    # `--processes 2`: a run per process, each numbered from 0
    two_processes = [*files[:2], files[2]._replace(run="run-b", sequence=0)]
    two_processes.append(files[3]._replace(run="run-b", sequence=1))
    assert logs_verdicts(two_processes, [], 60.0, 15.0, 16, 0, processes=2)[4].ok
    assert not logs_verdicts(two_runs, [], 60.0, 15.0, 16, 0, processes=2)[4].ok
    assert not logs_verdicts(files, [], 60.0, 15.0, 16, 0, processes=2)[4].ok
    gap = [*files[:3], files[3]._replace(sequence=4)]
    assert not logs_verdicts(gap, [], 60.0, 15.0, 16, 0)[4].ok
    untagged = [f._replace(run=None) for f in files]
    assert not logs_verdicts(untagged, [], 60.0, 15.0, 16, 0)[4].ok
    # poses missing from the files are allowed only as far as the recorder reported overflow
    assert logs_verdicts(files, [], 60.0, 15.0, 20, 4)[3].ok
    assert not logs_verdicts(files, [], 60.0, 15.0, 20, 3)[3].ok
    assert not logs_verdicts(files, [], 60.0, 15.0, 12, 0)[3].ok  # more recorded than published


def test_exit_code_judges_memory_and_queues_only_on_long_runs() -> None:
    t = np.arange(0, 2, 1 / 12)
    leak = memory_verdict(t, 400 + 10 * t, warmup_minutes=0.5)
    assert exit_code([leak, counted_verdict(10, 10, 0, 0)], minutes=1) == 0
    assert exit_code([leak], minutes=30) == 1
    assert exit_code([counted_verdict(10, 9, 0, 0)], minutes=1) == 1
    # a short run says so rather than FAIL for a trend it cannot show; a long one fails it
    assert outcome(leak, 1) == "not judged" and outcome(leak, 30) == "FAIL"
    assert outcome(counted_verdict(10, 9, 0, 0), 1) == "FAIL"
    assert outcome(counted_verdict(10, 10, 0, 0), 1) == "pass"


def test_latency_histogram_percentiles() -> None:
    hist = LatencyHistogram()
    assert math.isnan(hist.percentile(50))
    hist.add(list(np.arange(1, 101, dtype=float)))  # 1 .. 100 ms
    hist.add([])
    assert hist.percentile(50) == pytest.approx(50.0, abs=0.11)
    assert hist.percentile(99) == pytest.approx(99.0, abs=0.11)
    hist.add([1e6])  # beyond the last bin: counted there
    assert hist.percentile(100) == pytest.approx(60_000.0)
