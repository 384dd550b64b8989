"""The pure parts of the soak benchmark (:mod:`bench.soak`): the verdicts.

A soak run is too long to precompute (100 robots for 30 minutes at 10 Hz is 18,000 scans each,
about 5 GB of JSON), so each robot drives its path out and back, over and over, with odometry
that goes on drifting (:mod:`service.sim.plan`): what the generator holds is fixed by the
path's length, not by the run's.

The verdicts take the sampled time series and return :class:`Verdict` values; ``hard`` ones
(scans counted, logs rotated and readable) decide the exit code of every run, the others (memory
slope, queues) only that of a long run (:data:`LONG_RUN_MINUTES`), where their targets apply.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from bench.procstat import MEMORY_PARTS

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Memory slope target after warm-up, MB per 10 minutes.
SLOPE_TARGET_MB_PER_10MIN = 1.0
#: Runs at least this long have their memory and queue verdicts count toward the exit code.
LONG_RUN_MINUTES = 10.0


# ---------------------------------------------------------------------------------- verdicts


class Verdict(NamedTuple):
    """One verdict of a soak run.

    Attributes:
        name: what is judged.
        ok: passed.
        detail: the figures it rests on.
        hard: decides the exit code of every run, not only of a long one.
    """

    name: str
    ok: bool
    detail: str
    hard: bool


def slope_per_10min(minutes: Sequence[float], values: Sequence[float]) -> float:
    """Least-squares slope of ``values`` against time, per 10 minutes (``nan`` below 2 points)."""
    t = np.asarray(minutes, dtype=float)
    v = np.asarray(values, dtype=float)
    keep = np.isfinite(t) & np.isfinite(v)
    t, v = t[keep], v[keep]
    if len(t) < 2 or np.ptp(t) == 0:
        return math.nan
    slope = np.polyfit(t, v, 1)[0]
    return float(slope * 10.0)


def halves_per_10min(minutes: Sequence[float], values: Sequence[float]) -> tuple[float, float]:
    """:func:`slope_per_10min` of the first and of the second half of the time the samples span.

    A leak grows in both halves; a heap that settles (its high-water mark reached once the
    run's rare bursts have all come) grows in the first and is flat in the second, which one
    slope over the whole run does not tell apart.
    """
    t = [x for x in minutes if math.isfinite(x)]
    if len(t) < 2:
        return math.nan, math.nan
    middle = (min(t) + max(t)) / 2.0
    first = [(x, v) for x, v in zip(minutes, values, strict=True) if x <= middle]
    second = [(x, v) for x, v in zip(minutes, values, strict=True) if x >= middle]
    return (
        slope_per_10min([x for x, _ in first], [v for _, v in first]),
        slope_per_10min([x for x, _ in second], [v for _, v in second]),
    )


def after_warmup(
    minutes: Sequence[float], values: Sequence[float], warmup_minutes: float
) -> tuple[list[float], list[float]]:
    """The samples taken at or after ``warmup_minutes``."""
    pairs = [(t, v) for t, v in zip(minutes, values, strict=True) if t >= warmup_minutes]
    return [t for t, _ in pairs], [v for _, v in pairs]


def memory_verdict(
    minutes: Sequence[float],
    rss_mb: Sequence[float],
    warmup_minutes: float,
    target: float = SLOPE_TARGET_MB_PER_10MIN,
) -> Verdict:
    """Resident memory slope after warm-up at most ``target`` MB per 10 minutes."""
    t, v = after_warmup(minutes, rss_mb, warmup_minutes)
    slope = slope_per_10min(t, v)
    ok = math.isfinite(slope) and slope <= target
    span = f"{len(t)} samples from minute {warmup_minutes:g}"
    rng = f"{min(v):.0f} to {max(v):.0f} MB" if v else "no samples"
    early, late = halves_per_10min(t, v)
    return Verdict(
        "memory slope after warm-up",
        ok,
        f"{slope:+.2f} MB per 10 min (target <= {target:g}; first half {early:+.2f}, second "
        f"half {late:+.2f}); {span}, {rng}",
        hard=False,
    )


def memory_by_process(samples: Sequence[dict[str, Any]], warmup_minutes: float) -> list[str]:
    """Where a service's memory is and where it grows: a Markdown table, a row per process
    (``mem_{process}_{part}`` of the samples), each part (``VmRSS``, ``RssAnon``, ``RssFile``,
    ``Pss``) as its first value after warm-up, its last, and its slope after warm-up."""
    first = samples[0] if samples else {}
    labels = [k[4:-4] for k in first if k.startswith("mem_") and k.endswith("_rss")]
    if not labels:
        return []
    minutes = [s["minute"] for s in samples]
    head = {
        "rss": "VmRSS",
        "anon": "RssAnon (heap)",
        "file": "RssFile (mapped files)",
        "pss": "Pss",
    }
    lines = [
        "| process | " + " | ".join(head[part] for part in MEMORY_PARTS) + " |",
        "| --- |" + " --- |" * len(head),
    ]
    for label in labels:
        cells = []
        for part in MEMORY_PARTS:
            values = [s[f"mem_{label}_{part}"] for s in samples]
            t, v = after_warmup(minutes, values, warmup_minutes)
            if not v:
                cells.append("no sample")
                continue
            slope = round(slope_per_10min(t, v), 2) + 0.0  # no "-0.00" for a flat part
            cells.append(f"{v[0]:.0f} -> {v[-1]:.0f} ({slope:+.2f} per 10 min)")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def queue_grows(values: Sequence[float], margin: float) -> bool:
    """A queue grows when the median of its last third is above the largest value of its first
    third by more than ``margin``.

    A bounded queue that fluctuates (bursts, a busy moment of the machine) has its last third's
    median within its earlier range; one that creeps up does not. Fewer than 3 samples: no trend.
    """
    v = [x for x in values if math.isfinite(x)]
    if len(v) < 3:
        return False
    third = len(v) // 3
    first, last = v[:third], v[-third:]
    return float(np.median(last)) > max(first) + margin


def queue_verdict(
    name: str,
    minutes: Sequence[float],
    values: Sequence[float],
    warmup_minutes: float,
    margin: float,
) -> Verdict:
    """No upward trend of a queue's length after warm-up (see :func:`queue_grows`)."""
    t, v = after_warmup(minutes, values, warmup_minutes)
    finite = [x for x in v if math.isfinite(x)]
    if not finite:
        return Verdict(f"{name} does not grow", True, "not reported by the service", hard=False)
    grows = queue_grows(finite, margin)
    third = max(len(finite) // 3, 1)
    return Verdict(
        f"{name} does not grow",
        not grows,
        f"max {max(finite):.0f}; first third max {max(finite[:third]):.0f}, last third median "
        f"{float(np.median(finite[-third:])):.0f} (grows if above first third max + {margin:g}); "
        f"slope {slope_per_10min(t, v):+.1f} per 10 min",
        hard=False,
    )


def overflow_verdict(
    minutes: Sequence[float], overflow: Sequence[float], warmup_minutes: float
) -> Verdict:
    """The recorder's queue never overflowed after warm-up (it is bounded by dropping)."""
    _, v = after_warmup(minutes, overflow, warmup_minutes)
    finite = [x for x in v if math.isfinite(x)]
    lost = int(finite[-1] - finite[0]) if len(finite) >= 2 else 0
    total = int(finite[-1]) if finite else 0
    return Verdict(
        "recorder queue never full after warm-up",
        lost == 0,
        f"{lost} messages not recorded after warm-up ({total} over the run)",
        hard=False,
    )


def counted_verdict(sent: int, poses: int, dropped: int, not_processed: int) -> Verdict:
    """Every scan sent answered (a pose received) or counted by the service."""
    uncounted = sent - poses - dropped - not_processed
    return Verdict(
        "every scan answered or counted",
        uncounted == 0 and dropped >= 0,
        f"{sent} sent = {poses} poses + {dropped} dropped + {not_processed} not processed "
        f"+ {uncounted} uncounted",
        hard=True,
    )


class FileCheck(NamedTuple):
    """One log file read end to end.

    Attributes:
        name: file name.
        size_bytes: its size.
        messages: messages read.
        indexed: messages its summary says it holds.
        poses: PoseEstimate messages read.
        span_s: first to last pose message, seconds.
        error: why it could not be read, or ``None``.
        run: the run its ``rlutf.run`` metadata names, or ``None``.
        sequence: its number within that run, or ``None``.
    """

    name: str
    size_bytes: int
    messages: int
    indexed: int
    poses: int
    span_s: float
    error: str | None
    run: str | None = None
    sequence: int | None = None


def expected_files(run_seconds: float, rotate_seconds: float) -> int:
    """Fewest finished files a run of ``run_seconds`` recording must leave (at least 2)."""
    return max(2, int(run_seconds // rotate_seconds))


def logs_verdicts(
    files: Sequence[FileCheck],
    parts: Sequence[str],
    run_seconds: float,
    rotate_seconds: float,
    poses_published: int,
    recorder_overflow: int,
    processes: int = 1,
) -> list[Verdict]:
    """Rotation happened, nothing is left as ``.part``, every file reads end to end, the pose
    messages of all files are the poses published (less what the recorder reported lost), and
    the files name one run per service process (each started once), each run's files numbered
    0, 1, 2 ... in file order.
    """
    need = expected_files(run_seconds, rotate_seconds)
    longest = max((f.span_s for f in files), default=math.nan)
    bad = [f for f in files if f.error is not None or f.messages != f.indexed]
    recorded = sum(f.poses for f in files)
    missing = poses_published - recorded
    runs = {f.run for f in files}
    numbers = [f.sequence for f in files]
    in_order = all(
        [f.sequence for f in files if f.run == run] == list(range(sum(f.run == run for f in files)))
        for run in runs
    )
    return [
        Verdict(
            "logs rotated",
            len(files) >= need,
            f"{len(files)} files (at least {need} for {run_seconds:.0f} s at "
            f"{rotate_seconds:g} s each); longest {longest:.1f} s of poses",
            hard=True,
        ),
        Verdict(
            "no .part file left",
            not parts,
            f"{len(parts)} left" + "".join(f"; {name}" for name in parts),
            hard=True,
        ),
        Verdict(
            "every file readable end to end",
            not bad and bool(files),
            f"{len(files) - len(bad)} of {len(files)} read, {sum(f.messages for f in files)} "
            "messages"
            + "".join(
                f"; {f.name}: {f.error or f'{f.messages} read, {f.indexed} indexed'}" for f in bad
            ),
            hard=True,
        ),
        Verdict(
            "poses recorded = poses published",
            0 <= missing <= recorder_overflow,
            f"{recorded} pose messages in the files, {poses_published} published, "
            f"{recorder_overflow} messages reported not recorded",
            hard=True,
        ),
        Verdict(
            "the files are one run per process, numbered in order",
            len(runs) == processes and None not in runs and in_order,
            f"{len(runs)} run(s) named ({', '.join(sorted(str(r)[:8] for r in runs))}); "
            f"file numbers {numbers}",
            hard=True,
        ),
    ]


def exit_code(verdicts: Sequence[Verdict], minutes: float) -> int:
    """1 when a hard verdict failed, or any failed on a long run; else 0."""
    return int(any(outcome(v, minutes) == "FAIL" for v in verdicts))


def outcome(verdict: Verdict, minutes: float) -> str:
    """``pass``, ``FAIL``, or ``not judged``: a trend verdict (memory slope, queues) that failed
    on a run shorter than :data:`LONG_RUN_MINUTES`, whose few samples after warm-up are no
    trend (CI's one-minute soak)."""
    if verdict.ok:
        return "pass"
    return "FAIL" if verdict.hard or minutes >= LONG_RUN_MINUTES else "not judged"


class LatencyHistogram:
    """Latencies in 0.1 ms bins up to 60 s (the last bin holds the rest): percentiles of a run of
    any length in fixed memory."""

    BIN_MS = 0.1
    BINS = 600_000

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, dtype=np.int64)

    def add(self, latencies_ms: Sequence[float] | FloatArray) -> None:
        """Count latencies (ms)."""
        if len(latencies_ms):
            idx = np.minimum(
                (np.asarray(latencies_ms, dtype=float) / self.BIN_MS).astype(np.int64),
                self.BINS - 1,
            )
            self.counts += np.bincount(np.maximum(idx, 0), minlength=self.BINS)

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (upper edge of its bin), ms; ``nan`` when empty."""
        total = int(self.counts.sum())
        if total == 0:
            return math.nan
        rank = max(1, math.ceil(q / 100.0 * total))
        return float((np.searchsorted(np.cumsum(self.counts), rank) + 1) * self.BIN_MS)
