"""An audit split between processes by robot: the same verdict, in a fraction of the time.

A replay of one run is one thread of Python: about 3,000 scans a second here, so a day of 100
robots at 10 Hz takes eight hours. The robots of a run are localized apart (each robot's poses
depend on its own inputs, the maps and the configuration, never on another robot's), so an
audit can give each of ``jobs`` processes a share of the robots: each reads the whole run,
handles every map and only its robots' inputs and recorded poses (the others' are skipped on the
topic or the pose's robot, before any update), and matches them as one process would
(:class:`service.logs.posematch.PoseMatch`). The shares' matches are merged: the robots are
apart, so the audit is the one a single process gives. Robots are dealt out by their messages,
the largest first, to the least loaded share; a robot that no channel names (a pose whose
``robot_id`` is not its topic's) is the first share's, which also counts what belongs to no
robot (maps, unreadable poses). The processes run at a lower priority (:data:`NICE`), so an
audit beside a live service takes only the cores the service leaves.

Only an audit is split: an output log, plots and a ROS 2 bag need every robot in one process
(``rlutf replay`` splits only without ``--out``, ``--plot`` and ``--ros2-out``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from service.logs.mcapread import LogError, LogFile, robot_topic
from service.logs.posematch import PoseMatch
from service.logs.replay import REPLAYED, ReplayResult, replay
from service.logs.replayconfig import ReplayConfig

#: Messages a share handles between two reports of its progress.
REPORT_EVERY = 2_000
#: Runs of fewer messages are replayed in one process: a process of the pool takes a second or
#: two to start (Python, numba's kernels from their cache), about what one process takes for
#: this many messages.
SPLIT_MIN_MESSAGES = 20_000


def deal(logs: Sequence[Path], jobs: int) -> list[set[str]]:
    """The robots of the logs in ``jobs`` shares of about equal messages (fewer shares when
    there are fewer robots; at least one)."""
    sizes: dict[str, int] = {}
    with ExitStack() as stack:
        for lf in (stack.enter_context(LogFile(p)) for p in logs):
            for ch in lf.channels():
                where = robot_topic(ch.topic) if ch.schema_name in REPLAYED else None
                if where is not None:
                    sizes[where.robot] = sizes.get(where.robot, 0) + ch.messages
    shares: list[set[str]] = [set() for _ in range(max(1, min(jobs, len(sizes))))]
    loads = [0] * len(shares)
    for robot in sorted(sizes, key=lambda r: (-sizes[r], r)):
        k = loads.index(min(loads))
        shares[k].add(robot)
        loads[k] += sizes[robot]
    return shares


_SHARED: dict[str, Any] = {}  # in a pool's process: what its initializer was given


#: Niceness the processes of a split audit add: an audit is batch work, and a live service on
#: the same host (an operator auditing its log folder) keeps the cores it needs.
NICE = 10


def _start(counters: Any) -> None:
    _SHARED["counters"] = counters
    if hasattr(os, "nice"):
        os.nice(NICE)


def _share(
    files: Sequence[Path], config: ReplayConfig, shares: list[set[str]], k: int
) -> tuple[str, Any]:
    """Share ``k``'s replay in a process of the pool: ``("ok", result)`` or ``("error", why)``
    (a log that cannot be read; the exception itself may not cross back)."""
    mine = shares[k]
    dealt = set().union(*shares)
    done = 0

    def progress(n: int) -> None:
        nonlocal done
        done += n
        if done % REPORT_EVERY == 0:
            _SHARED["counters"][k] = done

    def owns(robot: str) -> bool:
        return robot in mine or (k == 0 and robot not in dealt)

    try:
        result = replay(
            files, config=config, keep=False, owns=owns, count_shared=k == 0, progress=progress
        )
    except LogError as err:
        return "error", str(err)
    _SHARED["counters"][k] = done
    result.maps.clear()  # the map payloads are not needed back, and may be large
    return "ok", result


def replay_split(
    files: Sequence[Path],
    config: ReplayConfig,
    jobs: int,
    progress: Callable[[int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    min_messages: int | None = None,
) -> ReplayResult:
    """The audit of one run's ``files`` by up to ``jobs`` processes (no output log, no poses
    kept): a :class:`ReplayResult` whose ``match`` and counts are those of :func:`replay` with
    ``keep=False``. A run of fewer than ``min_messages`` (default
    :data:`SPLIT_MIN_MESSAGES`) is replayed here, in one process.

    Raises:
        service.logs.mcapread.LogError: a file cannot be read.
    """
    with ExitStack() as stack:
        total = sum(stack.enter_context(LogFile(p)).count(REPLAYED) for p in files)
    least = SPLIT_MIN_MESSAGES if min_messages is None else min_messages
    shares = deal(files, jobs) if total >= least else [set()]
    if len(shares) == 1:
        return replay(files, config=config, keep=False, progress=progress, on_total=on_total)
    if on_total is not None:
        on_total(total)  # each share reads every message: shown, the slowest share's
    ctx = mp.get_context("spawn")
    counters = ctx.Array("q", len(shares), lock=False)
    with ProcessPoolExecutor(len(shares), ctx, initializer=_start, initargs=(counters,)) as pool:
        futures = [pool.submit(_share, files, config, shares, k) for k in range(len(shares))]
        try:
            _follow(futures, counters, progress)
        except BaseException:  # Ctrl-C: stop the shares, not wait for them to finish the audit
            _stop(pool)
            raise
        answers = [f.result() for f in futures]
    for kind, value in answers:
        if kind == "error":
            raise LogError(value)
    return merge([value for _, value in answers])


def _stop(pool: ProcessPoolExecutor) -> None:
    """End the pool's processes now (a SIGINT to this process alone, as ``kill -INT`` or
    ``timeout -s INT`` send, reaches none of them: the pool waited for every share to finish
    its whole audit, hours for a day's log)."""
    for proc in list(pool._processes.values()):
        proc.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def _follow(
    futures: list[Future[Any]], counters: Any, progress: Callable[[int], None] | None
) -> None:
    shown = 0
    while not all(f.done() for f in futures):
        time.sleep(0.2)
        if progress is not None:
            now = min(counters)
            progress(now - shown)
            shown = now
    if progress is not None:
        progress(min(counters) - shown)


def merge(results: Sequence[ReplayResult]) -> ReplayResult:
    """The result of the shares of one audit (robots apart) as one."""
    first = results[0]
    match = PoseMatch(first.gap_ns)
    merged = ReplayResult(first.config, match=match, keep=False, gap_ns=first.gap_ns)
    merged.completeness = first.completeness  # each share read every file whole
    for r in results:
        match.merge(r.match)
        merged.inputs += r.inputs
        merged.dropped += r.dropped
        merged.rejected += r.rejected
        merged.unreadable_poses += r.unreadable_poses
    return merged  # no MapHealth: each share saw only its robots' evidence
