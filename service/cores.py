"""How many cores the service may use (what ``workers = -1``, "one per core", counts), and how
much memory it can still be given (:func:`available_memory`: the system's, capped by a
container's memory limit as the cores are by its CPU quota).

``os.cpu_count()`` is the machine's cores. In a container it is the node's: a pod limited to
2 CPUs on a 64-core node would start 64 worker processes, each with its own copy of the
localizer's kernels (about 75 MB of private memory), and be killed at its memory limit before it
serves, or throttled to a crawl by its CPU quota. The cores a process may use are fewer than the
machine's in two ways, and :func:`usable_cores` takes both:

- its CPU affinity (``taskset``, ``docker --cpuset-cpus``, Kubernetes' static CPU manager):
  :func:`os.sched_getaffinity`;
- its cgroup's CPU bandwidth quota (``docker --cpus``, a Kubernetes CPU limit): ``cpu.max`` in
  cgroup v2 (``"QUOTA PERIOD"`` or ``"max PERIOD"``), ``cpu.cfs_quota_us`` and
  ``cpu.cfs_period_us`` in cgroup v1 (quota ``-1``: none), on the process's cgroup or any cgroup
  above it (each limits the ones below), rounded up: a quota of 1.5 CPUs is 2 cores.

The kernel's documents: Documentation/admin-guide/cgroup-v2.rst ("cpu.max") and
Documentation/scheduler/sched-bwc.rst (cgroup v1).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any

#: Where the cgroup file systems are mounted.
CGROUP_ROOT = Path("/sys/fs/cgroup")
#: The calling process's cgroups, one line per hierarchy: ``ID:CONTROLLERS:PATH``.
PROC_CGROUP = Path("/proc/self/cgroup")
#: Where a cgroup v1 hierarchy with the ``cpu`` controller may be mounted under the root.
_V1_CPU_DIRS = ("cpu", "cpu,cpuacct", "cpuacct,cpu")
#: cgroup v1's ``memory.limit_in_bytes`` at and above this (a page-rounded 2^63) is no limit.
_V1_NO_LIMIT = 2**62


def usable_cores(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_CGROUP) -> int:
    """The cores this process may use: its CPU affinity, capped by its cgroup's CPU quota.

    At least 1. Where a file cannot be read or parsed (no cgroups, another system), that limit
    is not applied.
    """
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        count = os.cpu_count() or 1
    quota = cpu_quota(root, proc_cgroup)
    if quota is not None:
        count = min(count, quota)
    return max(1, count)


def cpu_quota(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_CGROUP) -> int | None:
    """The smallest CPU bandwidth quota on this process's cgroups, in whole cores (rounded up);
    ``None`` if there is none.

    A cgroup v2 quota is looked for first; cgroup v1 only where no ``cpu.max`` was found (a
    host with both mounts has its controllers in one of them)."""
    v2_path, v1_path = _cgroup_paths(proc_cgroup, "cpu")
    found_v2, quotas = False, []
    if v2_path is not None:
        for cgroup in _self_and_ancestors(root, v2_path):
            text = _read(cgroup / "cpu.max")
            if text is None:
                continue
            found_v2 = True
            quota = _cores(*text.split()[:2]) if len(text.split()) == 2 else None
            if quota is not None:
                quotas.append(quota)
    if not found_v2 and v1_path is not None:
        for name in _V1_CPU_DIRS:
            for cgroup in _self_and_ancestors(root / name, v1_path):
                quota_text = _read(cgroup / "cpu.cfs_quota_us")
                period_text = _read(cgroup / "cpu.cfs_period_us")
                if quota_text is None or period_text is None:
                    continue
                quota = _cores(quota_text, period_text)
                if quota is not None:
                    quotas.append(quota)
    return min(quotas) if quotas else None


def _self_and_ancestors(mount: Path, path: str) -> list[Path]:
    """``mount/path`` and each directory above it, up to ``mount`` itself."""
    parts = PurePosixPath("/", path).parts[1:]
    return [mount.joinpath(*parts[:n]) for n in range(len(parts), -1, -1)]


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _cores(quota: str, period: str) -> int | None:
    """Whole cores of a quota and period in microseconds; ``None`` for no quota."""
    try:
        q, p = int(quota), int(period)
    except ValueError:  # "max": no quota
        return None
    if q <= 0 or p <= 0:  # cgroup v1's -1: no quota
        return None
    return max(1, math.ceil(q / p))


#: The kernel's figure of the memory it can give without swapping.
MEMINFO = Path("/proc/meminfo")


def available_memory(
    meminfo: Path = MEMINFO, root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_CGROUP
) -> int | None:
    """The memory this process can still be given, bytes: the system's ``MemAvailable``,
    capped by its cgroups' memory limits less what they use (a container's limit is far below
    the node's free memory); ``None`` where neither can be read (not Linux)."""
    free = None
    try:
        with meminfo.open() as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    free = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        free = None
    room = memory_room(root, proc_cgroup)
    if room is None:
        return free
    return room if free is None else min(free, room)


def memory_room(root: Path = CGROUP_ROOT, proc_cgroup: Path = PROC_CGROUP) -> int | None:
    """The least headroom (limit less usage, bytes) of this process's cgroup and those above it
    that have a memory limit; ``None`` if none has. Cgroup v2 (``memory.max``,
    ``memory.current``) first; v1 (``memory.limit_in_bytes``, ``memory.usage_in_bytes``, under
    the ``memory`` mount) where v2 has no memory controller."""
    v2_path, v1_path = _cgroup_paths(proc_cgroup, "memory")
    rooms: list[int] = []
    found_v2 = False
    if v2_path is not None:
        for cgroup in _self_and_ancestors(root, v2_path):
            limit, used = _read(cgroup / "memory.max"), _read(cgroup / "memory.current")
            if limit is None:
                continue
            found_v2 = True
            if limit.isdigit() and used is not None and used.isdigit():
                rooms.append(max(0, int(limit) - int(used)))
    if not found_v2 and v1_path is not None:
        for cgroup in _self_and_ancestors(root / "memory", v1_path):
            limit = _read(cgroup / "memory.limit_in_bytes")
            used = _read(cgroup / "memory.usage_in_bytes")
            if limit is None or used is None or not (limit.isdigit() and used.isdigit()):
                continue
            if int(limit) < _V1_NO_LIMIT:
                rooms.append(max(0, int(limit) - int(used)))
    return min(rooms) if rooms else None


def _cgroup_paths(proc_cgroup: Path, controller: str) -> tuple[str | None, str | None]:
    """This process's cgroup v2 path and its v1 path for ``controller`` (``None``: none)."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None, None
    v2_path, v1_path = None, None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        hierarchy, controllers, path = parts
        if hierarchy == "0" and controllers == "":
            v2_path = path
        elif controller in controllers.split(","):
            v1_path = path
    return v2_path, v1_path


#: Memory one more service or worker process needs at the least, bytes: its own heap and the
#: localizer's kernels (75-120 MB private at 50-100 robots, BENCHMARKS.md "Memory per
#: process"; the shared libraries are in memory once).
PROCESS_BYTES = 100 * 2**20


def layout_problem(
    settings: Any,
    cores: int | None = None,
    free_memory: Callable[[], int | None] = available_memory,
) -> tuple[str | None, str | None]:
    """``(refusal, warning)`` about the processes ``settings`` start: refused when they would
    need more than half the memory the machine has available (a typo such as ``--workers 200``
    would start 200 processes and wake the OOM killer), warned of when they are more than twice
    the usable cores (each localizes about as much as a core does: more add memory, not
    throughput). ``cores`` and ``free_memory`` (``None``: not known): this machine's unless
    given."""
    cores = usable_cores() if cores is None else cores
    processes = settings.service_processes(cores)
    if processes > 0:
        flag, count = "--processes", processes
    else:
        flag, count = "--workers", cores if settings.workers < 0 else settings.workers
    free = free_memory()
    need = (count + (flag == "--workers")) * PROCESS_BYTES  # the workers' own process too
    if free is not None and need > free // 2:
        return (
            f"{flag} {count}: {count} processes need at least {need / 2**30:.1f} GB, more than "
            f"half the {free / 2**30:.1f} GB this machine has available; each localizes about "
            f"as much as one core, and {cores} are usable here: {flag} {cores} or fewer",
            None,
        )
    if count > 2 * cores:
        return None, (
            f"{flag} {count} on {cores} usable cores: more processes than cores add memory "
            f"(at least {PROCESS_BYTES // 2**20} MB each), not throughput"
        )
    return None, None
