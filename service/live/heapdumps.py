"""Snapshots of Python's allocations on a signal: what grows in a long run, per process.

With ``RLUTF_TRACEMALLOC=N`` (N >= 1) in its environment, every process of ``rlutf serve``
traces Python's allocations from its start (:mod:`tracemalloc`, N frames of each allocation's
stack) and, on ``SIGUSR2``, writes a snapshot to ``$RLUTF_TRACEMALLOC_DIR`` (default: the
working folder) as ``rlutf-{pid}-{n}.tracemalloc``, n counting from 1. Compare two snapshots of
one process with :func:`grown` (``python -m bench.soak --tracemalloc 1`` takes one after the
warm-up and one at the end, and writes what grew). Tracing costs every allocation some CPU and
memory of its own: a diagnosis tool, not for a fleet in service. Memory outside Python's
allocator (numpy buffers are traced; Zenoh's and glibc's arenas are not) does not show here.
"""

from __future__ import annotations

import logging
import os
import signal
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

ENV_FRAMES = "RLUTF_TRACEMALLOC"
ENV_DIR = "RLUTF_TRACEMALLOC_DIR"
#: The environment variables of this diagnosis (a host passes them on to its processes).
TRACE = (ENV_FRAMES, ENV_DIR)
SUFFIX = ".tracemalloc"


def install_from_env() -> bool:
    """Start tracing and dump on ``SIGUSR2`` if ``RLUTF_TRACEMALLOC`` asks for it (main
    thread only). Returns whether it did."""
    text = os.environ.get(ENV_FRAMES, "").strip()
    if not text:
        return False
    try:
        frames = int(text)
    except ValueError:
        frames = 0
    if not 1 <= frames <= 100:
        log.warning("%s=%r: expected 1 to 100 frames; not tracing", ENV_FRAMES, text)
        return False
    folder = Path(os.environ.get(ENV_DIR) or ".")
    taken = 0

    def dump(_signum: int, _frame: object) -> None:
        nonlocal taken
        taken += 1
        path = folder / f"rlutf-{os.getpid()}-{taken}{SUFFIX}"
        try:
            tracemalloc.take_snapshot().dump(str(path))
        except OSError as err:
            log.warning("tracemalloc snapshot %s: %s", path, err)
        else:
            log.info("tracemalloc snapshot written: %s", path)

    tracemalloc.start(frames)
    signal.signal(signal.SIGUSR2, dump)
    return True


def snapshots(folder: Path, pid: int) -> list[Path]:
    """The snapshots a process wrote into ``folder``, in the order it took them."""
    found = folder.glob(f"rlutf-{pid}-*{SUFFIX}")
    return sorted(found, key=lambda p: int(p.name[: -len(SUFFIX)].rsplit("-", 1)[1]))


@dataclass(frozen=True)
class Growth:
    """Where a process's traced allocations grew between two snapshots."""

    where: str  # file:line of the allocation (its innermost frame)
    kb: float  # size after less size before, kB
    blocks: int  # allocations after less before
    kb_after: float


def grown(before: Path, after: Path, top: int = 10) -> tuple[float, list[Growth]]:
    """Total growth of the traced allocations (kB) and its ``top`` largest places."""
    first = tracemalloc.Snapshot.load(str(before))
    last = tracemalloc.Snapshot.load(str(after))
    stats = last.compare_to(first, "lineno")
    total = sum(s.size_diff for s in stats) / 1e3
    rows = []
    for s in sorted(stats, key=lambda s: s.size_diff, reverse=True)[:top]:
        where = f"{s.traceback[0].filename}:{s.traceback[0].lineno}"
        rows.append(Growth(where, s.size_diff / 1e3, s.count_diff, s.size / 1e3))
    return total, rows
