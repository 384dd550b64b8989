"""A process tree's resident memory and CPU time, and the machine's stolen CPU (from ``/proc``).

What the fleet benchmarks (:mod:`bench.fleet`, :mod:`bench.soak`) read of the service they
measure, without a library: Linux's counters as they are.
"""

from __future__ import annotations

import math
import os


def children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (each of its threads' ``children``: no scan of every
    process of the machine, cheap enough to sample a tree every 50 ms)."""
    found: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:  # the process ended
        return found
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                found += [int(c) for c in f.read().split()]
        except OSError:
            continue
    return found


def _cmdline(pid: int) -> bytes | None:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read()
    except OSError:
        return None


def descendants(pid: int) -> list[int]:
    """Process ids of ``pid``'s children, their children, and so on; without a child between
    fork and exec (its command line still its parent's: every process the service starts is
    spawned or exec'd), whose resident pages are its parent's and would count twice."""
    found = []
    todo = [(c, _cmdline(pid)) for c in children(pid)]
    while todo:
        p, parent_cmdline = todo.pop()
        cmdline = _cmdline(p)
        if cmdline is None or cmdline == parent_cmdline:
            continue
        found.append(p)
        todo += [(c, cmdline) for c in children(p)]
    return found


def _kb_mb(pids: list[int], name: str, field: str) -> float:
    """The ``field`` line (kB) of ``/proc/PID/{name}`` added up over ``pids``, MB (processes
    gone meanwhile count 0)."""
    total = 0
    for p in pids:
        try:
            with open(f"/proc/{p}/{name}") as f:
                total += next((int(line.split()[1]) for line in f if line.startswith(field)), 0)
        except OSError:
            continue
    return total / 1024.0


def rss_tree_mb(pid: int) -> float:
    """Resident memory of a process and its descendants, MB (``VmRSS`` added up: a library
    mapped by several counts in each)."""
    return _kb_mb([pid, *descendants(pid)], "status", "VmRSS:")


def pss_tree_mb(pid: int) -> float:
    """Proportional resident memory of a process and its descendants, MB: each shared page
    (a library mapped by several of them) divided among the processes that map it, so the
    sum is what the tree takes from the machine (``Pss`` in ``smaps_rollup``)."""
    return _kb_mb([pid, *descendants(pid)], "smaps_rollup", "Pss:")


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time of one process so far, seconds (``nan`` once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def machine_steal() -> tuple[int, int]:
    """CPU time stolen by the hypervisor and all CPU time of the machine so far, in ticks.

    On a shared virtual machine, other guests take CPU time that never shows in this
    machine's load; when they do, latency and CPU per scan rise without any change here.
    """
    with open("/proc/stat") as f:
        ticks = [int(v) for v in f.readline().split()[1:]]
    return ticks[7], sum(ticks[:8])


#: The ``/proc`` fields that :func:`process_memory_mb` reads, and the names it gives them.
_MEMORY_FIELDS = {"VmRSS:": "rss", "RssAnon:": "anon", "RssFile:": "file", "Pss:": "pss"}
#: The parts of a process's resident memory that :func:`process_memory_mb` returns.
MEMORY_PARTS = tuple(_MEMORY_FIELDS.values())


def labelled_processes(pid: int) -> dict[str, int]:
    """``pid`` as ``host`` and its children as ``p1``, ``p2``, ... (by process id): the names
    under which a benchmark reports each process of a service's tree."""
    return {"host": pid, **{f"p{k}": c for k, c in enumerate(sorted(children(pid)), start=1)}}


def process_memory_mb(pid: int) -> dict[str, float] | None:
    """A process's resident memory, MB: ``rss`` (``VmRSS``), its parts ``anon`` (``RssAnon``)
    and ``file`` (``RssFile``), and ``pss`` (shared pages divided among the processes mapping
    them, from ``smaps_rollup``); ``None`` once it is gone."""
    keys = _MEMORY_FIELDS
    found: dict[str, float] = {}
    try:
        for name in (f"/proc/{pid}/status", f"/proc/{pid}/smaps_rollup"):
            with open(name) as f:
                for line in f:
                    field = line.split(maxsplit=2)
                    if field and field[0] in keys:
                        found[keys[field[0]]] = int(field[1]) / 1024.0
    except OSError:
        return None
    return found if len(found) == len(keys) else None
