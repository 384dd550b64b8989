"""The cores ``workers = -1`` counts: CPU affinity capped by a container's CPU quota."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from service.config import Settings
from service.cores import available_memory, cpu_quota, layout_problem, memory_room, usable_cores
from service.keys import Keys
from service.live.dispatch import Dispatcher


def _tree(root: Path, files: dict[str, str], cgroup: str) -> Path:
    """Cgroup files under ``root`` and a /proc/self/cgroup that puts the process in ``cgroup``."""
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")
    proc = root / "proc-self-cgroup"
    proc.write_text(cgroup)
    return proc


def _affinity() -> int:
    return len(os.sched_getaffinity(0))


def test_v2_quota_of_the_process_cgroup_rounds_up(tmp_path: Path) -> None:
    proc = _tree(tmp_path, {"kubepods/pod1/c1/cpu.max": "150000 100000"}, "0::/kubepods/pod1/c1\n")
    assert cpu_quota(tmp_path, proc) == 2  # 1.5 CPUs: 2 cores
    assert usable_cores(tmp_path, proc) == min(_affinity(), 2)


def test_v2_an_ancestor_limits_the_cgroups_below_it(tmp_path: Path) -> None:
    files = {
        "kubepods/cpu.max": "max 100000",
        "kubepods/pod1/cpu.max": "100000 100000",  # 1 CPU for the pod
        "kubepods/pod1/c1/cpu.max": "max 100000",  # no limit of the container's own
    }
    proc = _tree(tmp_path, files, "0::/kubepods/pod1/c1\n")
    assert cpu_quota(tmp_path, proc) == 1
    assert usable_cores(tmp_path, proc) == 1


def test_v2_a_container_sees_its_own_cgroup_at_the_root(tmp_path: Path) -> None:
    # With a cgroup namespace the process is at "/" and the mount is its container's cgroup;
    # without one, /proc says the host's path and only the mount's root file exists.
    proc = _tree(tmp_path, {"cpu.max": "50000 100000"}, "0::/\n")
    assert cpu_quota(tmp_path, proc) == 1  # half a CPU: still one worker
    proc = _tree(tmp_path, {"cpu.max": "200000 100000"}, "0::/system.slice/docker-ab.scope\n")
    assert cpu_quota(tmp_path, proc) == 2


def test_no_quota_is_the_affinity(tmp_path: Path) -> None:
    proc = _tree(tmp_path, {"a/cpu.max": "max 100000"}, "0::/a\n")
    assert cpu_quota(tmp_path, proc) is None
    assert usable_cores(tmp_path, proc) == _affinity()
    assert usable_cores(tmp_path, tmp_path / "no-such-file") == _affinity()


def test_v1_quota(tmp_path: Path) -> None:
    files = {
        "cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "300000",
        "cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000",
    }
    text = "12:memory:/docker/abc\n4:cpu,cpuacct:/docker/abc\n1:name=systemd:/docker/abc\n"
    proc = _tree(tmp_path, files, text)
    assert cpu_quota(tmp_path, proc) == 3
    files = {"cpu/cpu.cfs_quota_us": "-1", "cpu/cpu.cfs_period_us": "100000"}
    proc = _tree(tmp_path / "none", files, "3:cpu:/\n")
    assert cpu_quota(tmp_path / "none", proc) is None


def test_v2_is_taken_before_v1(tmp_path: Path) -> None:
    files = {
        "cpu.max": "100000 100000",
        "cpu/cpu.cfs_quota_us": "400000",
        "cpu/cpu.cfs_period_us": "100000",
    }
    proc = _tree(tmp_path, files, "3:cpu:/\n0::/\n")
    assert cpu_quota(tmp_path, proc) == 1


@pytest.mark.parametrize("text", ["", "garbage", "12 x", "0 100000", "100000 0", "\xff"])
def test_unreadable_quota_is_no_limit(tmp_path: Path, text: str) -> None:
    proc = _tree(tmp_path, {"cpu.max": text}, "0::/\n")
    assert cpu_quota(tmp_path, proc) is None
    assert usable_cores(tmp_path, proc) >= 1


def test_this_machine() -> None:
    quota = cpu_quota()
    expected = _affinity() if quota is None else min(_affinity(), quota)
    assert usable_cores() == max(1, expected)


def test_workers_minus_one_counts_usable_cores() -> None:
    s = Settings()
    assert s.workers == -1
    d = Dispatcher(Keys(), s.localizer, -1, 0, lambda *a: None, lambda *a: None)
    assert len(d.shards) == usable_cores()  # made, not started: no process yet


GIB = 2**30


def test_a_layout_past_half_the_free_memory_is_refused() -> None:
    # A typo (`--workers 200`, robots meant) would start 200 processes and wake the OOM killer.
    refusal, _ = layout_problem(Settings(workers=200), cores=2, free_memory=lambda: 8 * GIB)
    assert refusal is not None
    assert refusal.startswith("--workers 200: 200 processes need at least 19.6 GB")
    assert "half the 8.0 GB" in refusal and "--workers 2 or fewer" in refusal
    refusal, _ = layout_problem(Settings(processes=64), cores=2, free_memory=lambda: 4 * GIB)
    assert refusal is not None and refusal.startswith("--processes 64:")


def test_the_default_layout_is_neither_refused_nor_warned_of() -> None:
    assert layout_problem(Settings(), cores=2, free_memory=lambda: 8 * GIB) == (None, None)
    one = Settings(workers=0, processes=0)
    assert layout_problem(one, cores=1, free_memory=lambda: GIB) == (None, None)


def test_more_processes_than_twice_the_cores_are_warned_of() -> None:
    refusal, warning = layout_problem(Settings(processes=8), cores=2, free_memory=lambda: 64 * GIB)
    assert refusal is None and warning is not None
    assert warning.startswith("--processes 8 on 2 usable cores: more processes than cores")
    four = Settings(workers=4)
    assert layout_problem(four, cores=2, free_memory=lambda: 64 * GIB) == (None, None)


def test_unknown_free_memory_refuses_nothing() -> None:
    refusal, warning = layout_problem(Settings(workers=200), cores=2, free_memory=lambda: None)
    assert refusal is None and warning is not None


def test_a_containers_memory_limit_caps_the_free_memory(tmp_path: Path) -> None:
    # A pod limited to 1 GiB on a node with 60 GiB free may start what fits in its limit.
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal: 99999999 kB\nMemAvailable: 62914560 kB\n")
    files = {"pod/memory.max": str(GIB), "pod/memory.current": str(300 * 2**20)}
    proc = _tree(tmp_path / "v2", files, "0::/pod\n")
    assert memory_room(tmp_path / "v2", proc) == GIB - 300 * 2**20
    assert available_memory(meminfo, tmp_path / "v2", proc) == GIB - 300 * 2**20
    free = lambda: available_memory(meminfo, tmp_path / "v2", proc)  # noqa: E731
    refusal, _ = layout_problem(Settings(workers=16), cores=16, free_memory=free)
    assert refusal is not None and "half the 0.7 GB" in refusal


def test_an_ancestor_and_cgroup_v1_limits_count_and_no_limit_is_none(tmp_path: Path) -> None:
    v2 = {"a/memory.max": "max", "a/memory.current": "5", "a/b/memory.max": "max"}
    v2 |= {"a/b/memory.current": "5", "memory.max": "2000", "memory.current": "1500"}
    proc = _tree(tmp_path / "v2", v2, "0::/a/b\n")
    assert memory_room(tmp_path / "v2", proc) == 500  # the root's limit holds below it
    unlimited = {"x/memory.max": "max", "x/memory.current": "5"}
    assert memory_room(tmp_path / "u", _tree(tmp_path / "u", unlimited, "0::/x\n")) is None
    v1 = {"memory/k/memory.limit_in_bytes": "1000", "memory/k/memory.usage_in_bytes": "400"}
    v1 |= {"memory/memory.limit_in_bytes": str(2**63 - 4096), "memory/memory.usage_in_bytes": "9"}
    proc = _tree(tmp_path / "v1", v1, "4:memory:/k\n0::/\n")
    assert memory_room(tmp_path / "v1", proc) == 600
    # nothing readable: the system's figure alone
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemAvailable: 1024 kB\n")
    assert available_memory(meminfo, tmp_path / "none", tmp_path / "missing") == 2**20
