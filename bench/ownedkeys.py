"""What a process pays for the robots it does not own: subscriptions per owned robot, measured.

Run: ``python -m bench.ownedkeys [--robots 200] [--duration 20] [--rounds 3] [--write]``.

Issue 21 expected the service's CPU per scan to fall if no process received every robot's
samples. Today each process of ``rlutf serve --processes 2`` subscribes to every robot's keys
(``{prefix}/robots/*/*``) and drops another's samples on the key, and its KeyWatch subscribes
to ``{prefix}/**`` (every sample again, into a ring its thread drains every 20 ms). This
benchmark measures the most that subscriptions per owned robot could save, before anyone builds
them, with three variants of the same service, run in turn:

- the service as it is;
- the same with no KeyWatch (what the KeyWatch costs on its own);
- each process subscribed only to its own robots' keys (``{prefix}/robots/{id}/*``, one FIFO
  channel each, polled by the input loop) and to every pose (``{prefix}/robots/*/pose``, which
  a handover needs), with no KeyWatch.

The owners are computed up front from the fleet's ids and the processes' names (the rendezvous
of :mod:`service.cluster.membership`), so the last variant leaves out what a real design would
add: discovery of new robots, the KeyWatch of one process, subscriptions declared and undeclared
on handovers, seeds without the odometry of robots owned elsewhere. It is an upper bound of the
saving, not a design: the patch is applied only to the benchmark's service (``sitecustomize`` in
``bench/ownedkeys_site``, on ``PYTHONPATH`` with :data:`ENV` set), never to ``rlutf``.

Each run is :func:`bench.fleetrun.run_size` (same fleet, 2 processes, recording on,
``--threads``); reported by variant: CPU per scan sent by process, the share answered and the
p99 after each robot's first 2 s, the Zenoh and KeyWatch threads' CPU per scan.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import statistics
import threading
from pathlib import Path
from typing import Any

from bench.report import section_main

SECTION = "ownedkeys"
#: Set in the service's environment: the processes' names, comma-separated, then ``;`` and the
#: robots' ids, comma-separated.
ENV = "BENCH_OWNED_KEYS"
SITE = Path(__file__).with_name("ownedkeys_site")
#: :data:`ENV`'s value for the middle variant: every robot's keys, no KeyWatch.
NO_WATCH = "no-keywatch"
#: This process's instance name, once its service starts (the patched input loop's owner).
PROCESS: dict[str, str] = {}
#: Channel per robot: a second of one robot's inputs.
PER_ROBOT = 64


def install() -> None:  # pragma: no cover - runs in the benchmark's service processes
    """Patch the input loop and the KeyWatch of this process as :data:`ENV` says."""
    spec = os.environ.get(ENV)
    if not spec:
        return
    import zenoh

    from service.live.keywatch import KeyWatch

    def no_watch(self: KeyWatch, session: zenoh.Session, stats: Any) -> None:
        self.stats = stats

    KeyWatch.start = no_watch  # type: ignore[method-assign]
    if spec == NO_WATCH:
        return

    from service.cluster.membership import owner_of
    from service.live import loop, node

    names, robots = (part.split(",") for part in spec.split(";"))
    start_service = node.LocalizationService.start

    def start(self: node.LocalizationService, *a: Any, **k: Any) -> node.LocalizationService:
        PROCESS["name"] = self.settings.instance
        return start_service(self, *a, **k)

    def start_loop(self: loop.InputLoop, session: zenoh.Session, key: str) -> None:
        prefix = key.split("/robots/", maxsplit=1)[0]
        mine = [r for r in robots if owner_of(r, names) == PROCESS["name"]]
        self._sub = session.declare_subscriber(
            f"{prefix}/robots/*/pose", zenoh.handlers.FifoChannel(loop.CAPACITY)
        )
        channels = [
            session.declare_subscriber(
                f"{prefix}/robots/{r}/*", zenoh.handlers.FifoChannel(PER_ROBOT)
            )
            for r in mine
        ]
        take = self._take

        def take_all() -> int:
            taken = take()
            for sub in channels:
                while (sample := sub.try_recv()) is not None:
                    taken += 1
                    self._on_sample(sample)
            return taken

        self._take = take_all  # type: ignore[method-assign]
        self._thread = threading.Thread(target=self._run, name="rlutf-inputs", daemon=True)
        self._thread.start()

    node.LocalizationService.start = start  # type: ignore[method-assign]
    loop.InputLoop.start = start_loop  # type: ignore[method-assign]


def owned_env(robots: int, processes: int) -> dict[str, str]:
    """The service's environment for the patched variant (names as the host gives them)."""
    from service.live.host import process_name

    names = ",".join(process_name("fleetbench", k) for k in range(processes))
    ids = ",".join(f"r{i:03d}" for i in range(robots))
    return {ENV: f"{names};{ids}", "PYTHONPATH": site_path()}


def site_path() -> str:
    """``PYTHONPATH`` for the patched service: the ``sitecustomize`` and the repository."""
    return os.pathsep.join((str(SITE), str(SITE.parent.parent)))


def cpu(row: dict[str, Any]) -> float:
    """Service CPU per scan sent, all processes, ms."""
    return float(row["cpu_main"] + row["cpu_workers"])


def run(args: argparse.Namespace) -> str:
    from bench.fleetrun import run_size

    size = functools.partial(run_size, args.robots, args.duration, True, 0, threads=True)
    flags = ("--processes", "2")
    args.load = os.getloadavg()[0]
    variants: dict[str, dict[str, str] | None] = {
        "every robot's keys (the service)": None,
        "every robot's keys, no KeyWatch": {ENV: NO_WATCH, "PYTHONPATH": site_path()},
        "owned robots' keys and every pose, no KeyWatch": owned_env(args.robots, 2),
    }
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in variants}
    for i in range(args.rounds):
        print(f"round {i + 1}/{args.rounds}", flush=True)
        for name, env in variants.items():
            rows[name].append(size(serve_flags=flags, env=env))
    return render(args, rows)


def render(args: argparse.Namespace, rows: dict[str, list[dict[str, Any]]]) -> str:
    load = getattr(args, "load", os.getloadavg()[0])
    out = [
        f"Command: `python -m bench.ownedkeys --robots {args.robots} --duration "
        f"{args.duration:g} --rounds {args.rounds} --write`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
        f"{platform.python_version()}. `rlutf serve --processes 2`, recording on, {args.robots} "
        f"robots at 10 Hz, {args.duration:g} s a run, the variants in turn "
        f"({args.rounds} rounds). Load average when the run started: {load:.1f}.",
        "",
        "| subscriptions | CPU ms per scan sent, all processes: each run | median | host / "
        "other process (median) | answered after the first 2 s, % (median) | p99 ms after the "
        "first 2 s (median) | Zenoh threads ms per scan (median) | KeyWatch ms per scan "
        "(median) |",
        "| --- | --- | ---: | --- | ---: | ---: | ---: | ---: |",
    ]
    medians = {}
    for name, runs in rows.items():
        total = [cpu(r) for r in runs]
        medians[name] = statistics.median(total)
        zenoh_ms = [
            sum(
                ms
                for table in r["threads"].values()
                for thread, ms in table.items()
                if thread.split("-")[0] in ("rx", "tx", "acc", "app", "net")
            )
            for r in runs
        ]
        watch = [sum(t.get("rlutf-keywatch", 0.0) for t in r["threads"].values()) for r in runs]
        out.append(
            f"| {name} | {', '.join(f'{c:.3f}' for c in total)} | {medians[name]:.3f} | "
            f"{statistics.median(r['cpu_main'] for r in runs):.2f} / "
            f"{statistics.median(r['cpu_workers'] for r in runs):.2f} | "
            f"{100 * statistics.median(r['answered_after'] for r in runs):.1f} | "
            f"{statistics.median(r['p99'] for r in runs):.1f} | "
            f"{statistics.median(zenoh_ms):.3f} | {statistics.median(watch):.3f} |"
        )
    before = next(iter(medians.values()))
    out.append("")
    out += [
        f"Saving of *{name}* (median against median): {before - m:.3f} ms of service CPU per "
        f"scan ({100 * (before - m) / before:.1f} %)."
        for name, m in list(medians.items())[1:]
    ]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m bench.ownedkeys",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=200, help="fleet size")
    p.add_argument("--duration", type=float, default=20.0, help="seconds a run")
    p.add_argument("--rounds", type=int, default=3, help="runs of each variant, in turn")
    return section_main(p, run, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
