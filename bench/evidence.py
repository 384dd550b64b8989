"""What one instance's map health evidence weighs on the bus, per second of a fleet.

Run: ``python -m bench.evidence [--robots 100] [--seconds 5] [--write]``.

Every instance of the service (each process of ``rlutf serve``) puts the map health evidence
its robots' scans counted on ``{prefix}/service/{instance}/mapevidence`` once a second, for the
others to merge (:mod:`service.evidence`). This drives a simulated fleet (:mod:`service.sim`,
360-beam scans at 10 Hz, the same plan as :mod:`bench.floor`) through one
:class:`service.engine.FleetEngine` with map health on, hands the evidence on once a second of
scans as a service does, and reports, per second: the cells touched, the payload raw and as
put (zstd level 1), the time to encode it and to decode it (:func:`service.evidence.
decode_evidence`, which checks it), medians over the seconds after the first.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import zstandard

from bench.report import section_main

SECTION = "evidence"


def measure(robots: int, seconds: int) -> list[tuple[int, int, int, float, float]]:
    """Per second of the fleet: (cells, raw bytes, bytes put, encode ms, decode ms)."""
    from bench.floor import _fleet, fleet_steps
    from service.evidence import decode_evidence, encode_evidence
    from service.live.worker import evidence

    plan, wire = _fleet(robots, 10 * seconds + 1)
    counted = evidence(True)
    step = fleet_steps(plan, wire, counted)
    rows = []
    for sec in range(seconds):
        for k in range(1 + 10 * sec, 11 + 10 * sec):
            step(k)
        handed = counted.take()
        t0 = time.perf_counter()
        payload = encode_evidence(handed)
        t1 = time.perf_counter()
        decode_evidence(payload)
        t2 = time.perf_counter()
        raw = len(zstandard.ZstdDecompressor().decompress(payload))
        cells = sum(len(h.counts.cells) for h in handed)
        rows.append((cells, raw, len(payload), (t1 - t0) * 1e3, (t2 - t1) * 1e3))
    return rows


def render(args: argparse.Namespace) -> str:
    rows = measure(args.robots, args.seconds)[1:]  # the first second: the kernels load
    med = [statistics.median(r[i] for r in rows) for i in range(5)]
    return "\n".join(
        [
            f"Command: `python -m bench.evidence --robots {args.robots} --seconds "
            f"{args.seconds} --write`",
            "",
            f"Machine: {platform.machine()}, CPython {platform.python_version()}; "
            f"{args.robots} simulated robots, 360-beam scans at 10 Hz, one simulated building; "
            f"medians over {len(rows)} seconds (the first left out).",
            "",
            "| robots | cells touched a second | raw KB | put KB (zstd 1) | ratio | encode ms "
            "| decode ms |",
            "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
            f"| {args.robots} | {med[0]:,.0f} | {med[1] / 1e3:,.0f} | {med[2] / 1e3:,.1f} | "
            f"{med[1] / med[2]:.0f} | {med[3]:.2f} | {med[4]:.2f} |",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m bench.evidence",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=100, help="simulated robots (default 100)")
    p.add_argument("--seconds", type=int, default=5, help="seconds of the fleet (default 5)")
    return section_main(p, render, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
