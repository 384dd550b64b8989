"""Where a running service's heap is, by kind of mapping, sampled beside a benchmark.

Run: ``python -m bench.smaps --minutes 21 --interval 60 [--pid PID]`` while a service runs (a
``python -m bench.soak`` started just before, say); it samples every process of the service's
tree (``host``, ``p1``, ...: :func:`bench.procstat.labelled_processes`) and prints, per process,
each kind's anonymous resident memory at each sample, MB.

``RssAnon`` (what :mod:`bench.soak` reports per process) is one figure. Which part of it moves
tells where to look: ``/proc/PID/smaps`` gives each mapping's ``Anonymous:`` pages, and three
kinds of mapping hold a Python service's heap:

- ``brk``: the ``[heap]`` mapping, glibc's main malloc arena (the main thread's allocations);
- ``arenas``: anonymous mappings that start on a 64 MiB boundary, glibc's other malloc arenas
  (each thread that allocates gets one, up to 8 per core: Zenoh's runtime threads, the service's
  own threads). glibc maps each arena's heap aligned to its 64 MiB maximum, which is how they are
  told apart; another mapping lands on such a boundary only by chance;
- ``other``: every other anonymous mapping (Python's object arenas, numpy's large arrays, thread
  stacks, allocations glibc maps on their own).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

from bench.procstat import labelled_processes

#: The kinds of mapping :func:`anon_by_kind` returns, in report order.
KINDS = ("brk", "arenas", "other")
#: glibc's arena heaps are mapped aligned to their maximum size (``HEAP_MAX_SIZE``, 64 MiB on a
#: 64-bit system).
ARENA_ALIGN = 64 << 20


def kind_of(start: int, name: str) -> str | None:
    """The kind of an anonymous mapping at address ``start`` named ``name`` (``None``: a file's
    mapping, or a special one other than ``[heap]``)."""
    if name == "[heap]":
        return "brk"
    if name:
        return None  # a file, [stack], [vdso], ...
    return "arenas" if start % ARENA_ALIGN == 0 else "other"


def anon_by_kind(smaps: str) -> dict[str, float]:
    """Anonymous resident memory of one process by kind (:data:`KINDS`), MB, from the text of
    its ``/proc/PID/smaps``."""
    out = dict.fromkeys(KINDS, 0.0)
    kind: str | None = None
    for line in smaps.splitlines():
        field = line.split()
        if not field:
            continue
        if not field[0].endswith(":"):  # a mapping's header: range, perms, offset, dev, inode, name
            start = int(field[0].split("-")[0], 16)
            kind = kind_of(start, field[5] if len(field) > 5 else "")
        elif field[0] == "Anonymous:" and kind is not None:
            out[kind] += int(field[1]) / 1024.0
    return out


def sample(pid: int) -> dict[str, dict[str, float]]:
    """Each process of ``pid``'s tree by label, its memory by kind (processes gone: left out)."""
    found = {}
    for label, p in labelled_processes(pid).items():
        try:
            with open(f"/proc/{p}/smaps") as f:
                found[label] = anon_by_kind(f.read())
        except OSError:
            continue
    return found


def table(samples: list[tuple[float, dict[str, dict[str, float]]]]) -> list[str]:
    """Markdown rows: a row per sample, a column per process and kind, MB."""
    labels = sorted({label for _, s in samples for label in s}, key=lambda x: (x != "host", x))
    head = [f"{label} {kind}" for label in labels for kind in KINDS]
    rows = ["| minute | " + " | ".join(head) + " |", "| ---: |" + " ---: |" * len(head)]
    for minute, s in samples:
        cells = [
            f"{s[label][kind]:.1f}" if label in s else "-" for label in labels for kind in KINDS
        ]
        rows.append(f"| {minute:.1f} | " + " | ".join(cells) + " |")
    return rows


def _service_pid() -> int | None:
    """The oldest ``rlutf serve`` process on this machine, if any."""
    run = subprocess.run(
        ["pgrep", "-o", "-f", "rlutf serve"], check=False, capture_output=True, text=True
    )
    return int(run.stdout.split()[0]) if run.stdout.split() else None


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.smaps",
        description=__doc__,
        formatter_class=argparse.RawTextHelpFormatter,
    )
    parser.add_argument("--minutes", type=float, default=20.0, help="how long to sample")
    parser.add_argument("--interval", type=float, default=60.0, help="seconds between samples")
    parser.add_argument(
        "--pid", type=int, default=None, help="the service's first process (default: the oldest "
        "`rlutf serve` process, waited for up to a minute)"
    )  # fmt: skip
    args = parser.parse_args(argv)
    pid = args.pid
    deadline = time.monotonic() + 60.0
    while pid is None and time.monotonic() < deadline:
        pid = _service_pid()
        if pid is None:
            time.sleep(1.0)
    if pid is None:
        print("bench.smaps: no `rlutf serve` process found", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    samples: list[tuple[float, dict[str, dict[str, float]]]] = []
    while (minute := (time.monotonic() - t0) / 60.0) <= args.minutes:
        found = sample(pid)
        if not found:
            break  # the service is gone
        samples.append((minute, found))
        print(f"[smaps {minute:5.1f} min] " + "; ".join(
            f"{label}: " + ", ".join(f"{k} {v:.1f}" for k, v in kinds.items())
            for label, kinds in found.items()
        ), flush=True)  # fmt: skip
        time.sleep(args.interval)
    print("\n".join(["", f"Anonymous resident memory by kind of mapping, MB (pid {pid}):", "",
                     *table(samples)]))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
