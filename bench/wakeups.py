"""What a thread wakeup and a pose put cost on this machine, apart from any work.

Run: ``python -m bench.wakeups [--seconds 0.5] [--write]``.

The service's CPU per scan is far above the localizer's update and the Python around it
(:mod:`bench.floor`), and it is higher at light load than at heavy load. Two costs that no
profile of Python shows explain part of it, and this benchmark measures them in isolation:

1. *A thread that wakes up*: a thread that waits (``threading.Event.wait`` with a timeout,
   ``time.sleep``) is charged CPU each time it resumes, more the longer it slept (caches and,
   on a virtual machine, the virtual CPU's resumption). Each thread of the service that waits
   for its next input pays it once per input or per timeout.
2. *A put on the bus*: a pose-sized put on a Zenoh publisher (a router session on a loopback
   port, a client session subscribed to it, as the service and a robot are). Isolated puts (one
   between a millisecond of other work, as a service that publishes each pose when it is made)
   cost several times what back-to-back puts cost.

Figures are the thread's own CPU time (``time.thread_time_ns``, the kernel's per-thread
accounting) per event, the median over :data:`BLOCKS` blocks; wall time beside it for the puts.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import threading
import time
from collections.abc import Callable

import numpy as np

from bench.report import section_main

SECTION = "wakeups"
#: Blocks per figure (the median of their means is reported).
BLOCKS = 5
#: Bytes of a pose put (a PoseEstimate's JSON is 600 to 800 bytes).
POSE_BYTES = 700
WAITS_S = (0.0002, 0.001, 0.005)


def wait_cost_us(wait_s: float, seconds: float) -> float:
    """On-CPU microseconds per wakeup of this thread from ``Event.wait(wait_s)``."""
    ev = threading.Event()
    n = max(int(seconds / BLOCKS / wait_s), 5)
    means = []
    for _ in range(BLOCKS):
        c0 = time.thread_time_ns()
        for _ in range(n):
            ev.wait(wait_s)
        means.append((time.thread_time_ns() - c0) / n / 1e3)
    return statistics.median(means)


def _busy(seconds: float, data: np.ndarray) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        data.sum()


def put_costs(gap_s: float, puts: int) -> tuple[float, float, int]:
    """(CPU, wall) microseconds per put of :data:`POSE_BYTES` bytes on a router session's
    publishers to a subscribed client, ``gap_s`` of numpy work between two puts, and how many
    of the timed puts the client received."""
    import zenoh

    from service.live.sessions import client_config, free_port, session_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(session_config("router", listen=[endpoint]))
    client = zenoh.open(client_config(endpoint))
    data = np.random.default_rng(0).random(2000)
    try:
        sub = client.declare_subscriber("wakeups/**", zenoh.handlers.FifoChannel(100_000))
        pubs = [
            router.declare_publisher(
                f"wakeups/r{i}/pose",
                congestion_control=zenoh.CongestionControl.DROP,
                express=False,
                allowed_destination=zenoh.Locality.REMOTE,
            )
            for i in range(50)
        ]
        _wait_for(lambda: _delivered(pubs[0], sub))
        payload = b"x" * POSE_BYTES
        cpu, wall = [], []
        received = 0
        per_block = puts // BLOCKS
        for _ in range(BLOCKS):
            c = w = 0
            for k in range(per_block):
                if gap_s:
                    _busy(gap_s, data)
                c0, w0 = time.thread_time_ns(), time.perf_counter_ns()
                pubs[k % len(pubs)].put(payload)
                c += time.thread_time_ns() - c0
                w += time.perf_counter_ns() - w0
            cpu.append(c / per_block / 1e3)
            wall.append(w / per_block / 1e3)
            end = time.monotonic() + 5.0
            got = 0
            while got < per_block and time.monotonic() < end:
                if sub.try_recv() is None:
                    time.sleep(0.001)
                else:
                    got += 1
            received += got
        return statistics.median(cpu), statistics.median(wall), received
    finally:
        client.close()
        router.close()


def _delivered(pub: object, sub: object) -> bool:
    pub.put(b"hello")  # type: ignore[attr-defined]
    time.sleep(0.05)
    return sub.try_recv() is not None  # type: ignore[attr-defined]


def _wait_for(ok: Callable[[], bool], timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not ok():
        if time.monotonic() > end:
            raise RuntimeError("the client never received the router's put")


def render(args: argparse.Namespace) -> str:
    """Measure and return the section."""
    started = time.time()
    puts = max(int(args.seconds / 0.001), 50)
    rows: list[tuple[str, float, str, str]] = [
        (
            f"a thread waking from `Event.wait({1e3 * w:g} ms)`",
            wait_cost_us(w, args.seconds),
            "-",
            "-",
        )
        for w in WAITS_S
    ]
    for label, gap in (
        ("a put, one after each 1 ms of other work (a pose as each update ends)", 0.001),
        ("a put, one after each 0.1 ms of other work", 0.0001),
        ("a put, back to back (poses put together)", 0.0),
    ):
        n = max(puts if gap else puts * 4, 10 * BLOCKS)
        cpu, wall, received = put_costs(gap, n)
        rows.append((label, cpu, f"{wall:.1f}", f"{received} of {n // BLOCKS * BLOCKS}"))
    return "\n".join(
        [
            f"Command: `python -m bench.wakeups --seconds {args.seconds:g} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}; {POSE_BYTES}-byte puts on a Zenoh router session to "
            f"a client on a loopback port, {puts} puts per row with other work between them "
            f"({puts * 4} back to back); each figure the median of {BLOCKS} blocks' means; "
            f"{time.time() - started:.0f} s in all. Load average at the end: "
            f"{os.getloadavg()[0]:.1f}.",
            "",
            "| event | CPU us of the thread, per event | wall us per event | received |",
            "| --- | ---: | ---: | ---: |",
            *(f"| {name} | {us:.1f} | {wall} | {got} |" for name, us, wall, got in rows),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.wakeups",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--seconds", type=float, default=0.5, help="time per wait row (puts: 1 per ms of it)"
    )
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
