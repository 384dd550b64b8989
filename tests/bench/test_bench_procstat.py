"""bench.procstat reads a process tree's memory from /proc: a child's pages count in the tree,
and Pss (shared pages divided among the processes mapping them) is below the VmRSS sum."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from bench.procstat import labelled_processes, process_memory_mb, pss_tree_mb, rss_tree_mb


def test_a_child_holding_memory_counts_in_its_parents_tree() -> None:
    alone_rss, alone_pss = rss_tree_mb(os.getpid()), pss_tree_mb(os.getpid())
    code = "import sys, time; b = bytearray(64 << 20); b[::4096] = b'x' * len(b[::4096]); "
    code += "print('ready', flush=True); time.sleep(30)"
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == b"ready"
        time.sleep(0.1)
        rss, pss = rss_tree_mb(os.getpid()), pss_tree_mb(os.getpid())
        labels = labelled_processes(os.getpid())
        assert labels["host"] == os.getpid() and child.pid in labels.values()
        part = process_memory_mb(child.pid)
        assert part is not None and part["anon"] > 60  # the bytearray is heap, not a file
        assert part["rss"] == pytest.approx(part["anon"] + part["file"], abs=1.0)
        assert rss - alone_rss > 60  # the child's 64 MB, touched
        assert pss - alone_pss > 60
        assert pss < rss  # the interpreter's shared pages count once in Pss, twice in VmRSS
    finally:
        child.kill()
        child.wait()
    assert rss_tree_mb(-1) == 0.0  # no such process: nothing, no error
