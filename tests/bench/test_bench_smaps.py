"""Anonymous memory by kind of mapping, from the text of ``/proc/PID/smaps``."""

from __future__ import annotations

import os

import pytest

from bench.smaps import anon_by_kind, kind_of, sample, table

_SMAPS = """\
5647fe806000-56480068f000 rw-p 00000000 00:00 0                          [heap]
Size:              31268 kB
Anonymous:         30000 kB
7f5f10000000-7f5f112d2000 rw-p 00000000 00:00 0
Size:              19272 kB
Anonymous:         10240 kB
7f5f112d2000-7f5f14000000 ---p 00000000 00:00 0
Size:              46264 kB
Anonymous:             0 kB
7f5f20001000-7f5f20101000 rw-p 00000000 00:00 0
Size:               1024 kB
Anonymous:          2048 kB
7f5f30000000-7f5f30400000 r-xp 00000000 fd:01 1234                       /usr/lib/libzenoh.so
Size:               4096 kB
Anonymous:           512 kB
7ffd1000000-7ffd1021000 rw-p 00000000 00:00 0                          [stack]
Size:                132 kB
Anonymous:           132 kB
"""


def test_the_heap_the_arenas_and_the_rest_are_told_apart() -> None:
    kinds = anon_by_kind(_SMAPS)
    # [heap] is brk; the 64 MiB-aligned mapping an arena (its PROT_NONE rest holds nothing); the
    # unaligned one other; a file's copied pages and the stack are none of them.
    assert kinds == pytest.approx({"brk": 30000 / 1024, "arenas": 10.0, "other": 2.0})
    assert kind_of(64 << 20, "") == "arenas" and kind_of((64 << 20) + 4096, "") == "other"
    assert kind_of(0, "/usr/lib/x.so") is None and kind_of(0, "[stack]") is None


def test_a_live_process_is_sampled_and_tabled() -> None:
    found = sample(os.getpid())
    assert set(found["host"]) == {"brk", "arenas", "other"}
    assert sum(found["host"].values()) > 1.0  # this interpreter's own heap
    rows = table([(0.0, found), (1.0, {})])
    assert rows[0].startswith("| minute | host brk | host arenas | host other")
    assert rows[-1] == "| 1.0 |" + " - |" * (3 * len(found))  # a sample with no process
