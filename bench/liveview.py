"""What the live view costs localization: the service's CPU per scan with and without a client.

Run: ``python -m bench.liveview [--robots 100] [--duration 15] [--write]`` (alone on the
machine: a timing).

The fleet benchmark's setup (:func:`bench.fleetrun.run_size`: a ``rlutf serve`` subprocess, a
load-generator process publishing odometry and a 360-beam scan per robot at 10 Hz) three times:
without ``--foxglove-port``; with it and no client; with it and a Foxglove WebSocket client (the
``websockets`` library speaking ``foxglove.sdk.v1``, in this process) subscribed to every channel
the server advertises (each robot's scan, pose and initial pose, the transforms, the fleet
status, the map) for the whole run. Reported: the service's CPU time per scan sent (main process
and workers), latency, drops, and the messages and bytes the client received.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import threading
import time
from typing import Any

from bench.fleetrun import run_size
from bench.report import section_main

SECTION = "liveview"


class Watcher(threading.Thread):
    """A Foxglove client that subscribes to every channel advertised and counts what comes."""

    def __init__(self, port: int) -> None:
        super().__init__(name="foxglove-watcher", daemon=True)
        self.url = f"ws://127.0.0.1:{port}"
        self.stop = threading.Event()
        self.messages = 0
        self.bytes = 0
        self.channels = 0

    def run(self) -> None:
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect
        from websockets.typing import Subprotocol

        while not self.stop.is_set():
            try:
                ws = connect(self.url, subprotocols=[Subprotocol("foxglove.sdk.v1")])
            except OSError:
                time.sleep(0.2)  # the service is not listening yet
                continue
            with ws, contextlib.suppress(ConnectionClosed):  # closed: the service stopped
                self._follow(ws)
            return

    def _follow(self, ws: Any) -> None:
        while not self.stop.is_set():
            try:
                frame = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    subs = [{"id": ch["id"], "channelId": ch["id"]} for ch in msg["channels"]]
                    self.channels += len(subs)
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            else:
                self.messages += 1
                self.bytes += len(frame)


def run(robots: int, duration: float, record: bool, workers: int) -> list[dict[str, Any]]:
    """The three configurations, in order."""
    from service.live.sessions import free_port

    results = []
    for name in ("off", "on, no client", "on, a client following everything"):
        flags: tuple[str, ...] = ()
        watcher = None
        if name != "off":
            port = free_port()
            flags = ("--foxglove-port", str(port))
            if "client" in name and "no client" not in name:
                watcher = Watcher(port)
                watcher.start()
        r = run_size(robots, duration, record, workers, serve_flags=flags, threads=True)
        if watcher is not None:
            watcher.stop.set()
            watcher.join(5)
            r["view"] = (watcher.channels, watcher.messages, watcher.bytes)
        r["name"] = name
        results.append(r)
        print(r["name"], r["cpu_main"], r["cpu_workers"], flush=True)
    return results


def view_threads(results: list[dict[str, Any]]) -> dict[str, float]:
    """CPU ms per scan sent of the service's threads that exist only with the view on.

    The refresh thread (``rlutf-foxglove``) and the SDK's server threads: every thread name of
    the main process in the last run that the run without the view did not have.
    """
    base = set(results[0]["threads"].get("main", {}))
    last = results[-1]["threads"].get("main", {})
    return {name: ms for name, ms in last.items() if name not in base}


def render(robots: int, duration: float, record: bool, workers: int) -> str:
    """Run and return the Markdown section."""
    load = os.getloadavg()[0]
    rows = []
    results = run(robots, duration, record, workers)
    for r in results:
        view = r.get("view")
        seen = f"{view[0]} channels, {view[1]} messages ({view[2] / 1e6:.0f} MB)" if view else "-"
        rows.append(
            f"| {r['name']} | {r['sent']} | {r['poses']} | {r['dropped']} "
            f"| {r['cpu_service_per_pose']:.2f} "
            f"| {r['cpu_main']:.2f} / {r['cpu_workers']:.2f} "
            f"| {r['p50']:.1f} / {r['p99']:.1f} | {r['steal']:.1f} | {seen} |"
        )
    flags = ("" if record else " --no-record") + (f" --workers {workers}" if workers >= 0 else "")
    view = view_threads(results)
    return "\n".join(
        [
            "## Live view: what a Foxglove client costs localization (issue 22)",
            "",
            f"Command: `python -m bench.liveview --robots {robots} "
            f"--duration {duration:g}{flags} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}. The fleet benchmark's setup (`bench.fleet`: one "
            f"`rlutf serve`, recording {'on' if record else 'off'}, and one load-generator "
            f"process, {robots} robots at 10 Hz, 360-beam scans, {duration:g} s) run three "
            "times: without `--foxglove-port`, with it and no client, and with a Foxglove "
            "WebSocket client (`websockets`, `foxglove.sdk.v1`, in the benchmark's process) "
            "subscribed to every channel for the whole run, at the default "
            "`foxglove_rate_hz` (10). CPU is the service's (main process and workers) over the "
            "publishing interval, per scan sent, and per pose the service reports processed. "
            f"Load average when the run started: {load:.1f} (2 cores: above 2, other work "
            "competed for them).",
            "",
            "| live view | scans sent | poses | dropped | service CPU ms per pose published "
            "| CPU ms per scan sent: main / workers | latency p50 / p99 ms | CPU stolen, % "
            "| what the client received |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            *rows,
            "",
            "The view's own threads with the client connected (CPU ms per scan sent, the "
            "kernel's per-thread counters; threads of the main process absent from the run "
            "without the view, Python names from `py-spy dump`):",
            "",
            "| thread | CPU ms per scan sent |",
            "| --- | ---: |",
            *[f"| {name} | {ms:.3f} |" for name, ms in sorted(view.items(), key=lambda i: -i[1])],
            f"| all of them | {sum(view.values()):.3f} |",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(
        prog="python -m bench.liveview",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=100, help="fleet size (default 100)")
    p.add_argument("--duration", type=float, default=15.0, help="seconds per configuration")
    p.add_argument("--no-record", action="store_true", help="service without MCAP recording")
    p.add_argument("--workers", type=int, default=-1, help="service worker processes")

    def go(args: argparse.Namespace) -> str:
        return render(args.robots, args.duration, not args.no_record, args.workers)

    return section_main(p, go, SECTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
