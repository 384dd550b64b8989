"""Where a process's CPU goes, thread by thread: ``/proc`` counters named by ``py-spy dump``.

A sampling profiler shows where threads are, not what they cost: a thread blocked in a pipe
read looks as busy as one compressing a chunk (py-spy's idle detection does not see through
every wait). The kernel's per-thread CPU counters (``/proc/PID/task/TID/stat``) do, and
``py-spy dump`` names the Python threads behind the thread ids (Zenoh's own threads carry their
names already). :func:`task_cpu` takes a snapshot; :func:`thread_table` turns two snapshots into
CPU per thread. :func:`task_switches` counts each thread's context switches likewise: on a
virtual machine a thread's wake-up costs tens of microseconds, so how often each thread sleeps
and wakes is the other half of where a process's CPU goes (BENCHMARKS.md, "Zenoh's runtimes in
a service process").
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections import defaultdict
from collections.abc import Iterator

_DUMP_THREAD = re.compile(r'^Thread (\d+) \([^)]*\): "([^"]*)"', re.MULTILINE)
_STATUS_NAME = re.compile(r"^Name:\t(.*)$", re.MULTILINE)
_SWITCHES = re.compile(r"^(?:non)?voluntary_ctxt_switches:\s+(\d+)$", re.MULTILINE)


def _tasks(pid: int, leaf: str) -> Iterator[tuple[int, str]]:
    """Each live thread of ``pid`` with the text of its ``/proc/PID/task/TID/{leaf}``."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/{leaf}") as f:
                yield int(tid), f.read()
        except OSError:  # the thread ended meanwhile
            continue


def task_cpu(pid: int) -> dict[int, tuple[str, float]]:
    """CPU seconds (user plus system) so far of each thread of ``pid``, with its kernel name."""
    out: dict[int, tuple[str, float]] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for tid, text in _tasks(pid, "stat"):
        name = text[text.index("(") + 1 : text.rindex(")")]
        fields = text.rsplit(")", 1)[1].split()
        out[tid] = (name, (int(fields[11]) + int(fields[12])) / tick)
    return out


def task_switches(pid: int) -> dict[int, tuple[str, float]]:
    """Context switches so far (voluntary and not) of each thread of ``pid``, with its kernel
    name: the same shape as :func:`task_cpu`'s, for :func:`thread_table` with ``scale`` 1."""
    out: dict[int, tuple[str, float]] = {}
    for tid, text in _tasks(pid, "status"):
        name = _STATUS_NAME.search(text)
        count = sum(int(n) for n in _SWITCHES.findall(text))
        out[tid] = (name.group(1) if name else str(tid), float(count))
    return out


def python_thread_names(pid: int) -> dict[int, str]:
    """Thread id to Python thread name, from ``py-spy dump`` (empty if py-spy is missing)."""
    exe = shutil.which("py-spy")
    if exe is None:
        return {}
    try:
        text = subprocess.run(
            [exe, "dump", "--pid", str(pid)],
            check=False,
            capture_output=True,
            text=True,
            timeout=30,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return {}
    return {int(tid): name for tid, name in _DUMP_THREAD.findall(text)}


def _role(name: str) -> str:
    """Group threads doing the same job: ``rlutf-shard-1-recv`` -> ``rlutf-shard-*-recv``."""
    if "pyo3-closure" in name:  # Python threads that zenoh runs callbacks on
        return "Zenoh callbacks (pyo3)"
    return re.sub(r"\d+", "*", name)


def thread_table(
    before: dict[int, tuple[str, float]],
    after: dict[int, tuple[str, float]],
    names: dict[int, str],
    per: int,
    scale: float = 1e3,
) -> list[tuple[str, float]]:
    """CPU milliseconds (or, ``scale`` 1 on :func:`task_switches`, switches) per unit of work
    (``per`` units) by thread role, largest first."""
    roles: dict[str, float] = defaultdict(float)
    for tid, (kernel_name, cpu) in after.items():
        spent = cpu - before.get(tid, (kernel_name, 0.0))[1]
        if spent > 0:
            roles[_role(names.get(tid, kernel_name))] += spent
    return sorted(((r, scale * s / max(per, 1)) for r, s in roles.items()), key=lambda x: -x[1])
