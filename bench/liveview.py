"""What the live view costs localization: the service's CPU per scan with and without a client.

Run: ``python -m bench.liveview [--robots 100] [--duration 15] [--write]`` (under
``flock /work/timing.lock`` on a shared machine).

The fleet benchmark's setup (:func:`bench.fleet.run_size`: a ``rlutf serve`` subprocess, a
load-generator process publishing odometry and a 360-beam scan per robot at 10 Hz) three times:
without ``--foxglove-port``; with it and no client; with it and a Foxglove WebSocket client (the
``websockets`` library speaking ``foxglove.sdk.v1``, in this process) subscribed to every channel
the server advertises (each robot's scan, pose and initial pose, the transforms, the fleet
status, the map) for the whole run. Reported: the service's CPU time per scan sent (main process
and workers), latency, drops, and the messages and bytes the client received.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import threading
import time
from typing import Any

from bench.fleet import run_size
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
        from websockets.sync.client import connect
        from websockets.typing import Subprotocol

        while not self.stop.is_set():
            try:
                ws = connect(self.url, subprotocols=[Subprotocol("foxglove.sdk.v1")])
            except OSError:
                time.sleep(0.2)  # the service is not listening yet
                continue
            with ws:
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
        t0 = time.monotonic()
        r = run_size(robots, duration, record, workers, serve_flags=flags)
        elapsed = time.monotonic() - t0
        if watcher is not None:
            watcher.stop.set()
            watcher.join(5)
            r["view"] = (watcher.channels, watcher.messages, watcher.bytes, elapsed)
        r["name"] = name
        results.append(r)
        print(r["name"], r["cpu_main"], r["cpu_workers"], flush=True)
    return results


def render(robots: int, duration: float, record: bool, workers: int) -> str:
    """Run and return the Markdown section."""
    load = os.getloadavg()[0]
    rows = []
    for r in run(robots, duration, record, workers):
        view = r.get("view")
        seen = (
            f"{view[0]} channels, {view[1]} messages ({view[2] / 1e6:.0f} MB), "
            f"{view[1] / view[3]:.0f}/s over the run"
            if view
            else "-"
        )
        rows.append(
            f"| {r['name']} | {r['sent']} | {r['poses']} | {r['dropped']} "
            f"| {r['cpu_main']:.2f} / {r['cpu_workers']:.2f} "
            f"| {r['cpu_main'] + r['cpu_workers']:.2f} "
            f"| {r['p50']:.1f} / {r['p99']:.1f} | {r['steal']:.1f} | {seen} |"
        )
    flags = ("" if record else " --no-record") + (f" --workers {workers}" if workers >= 0 else "")
    return "\n".join(
        [
            "## Live view: what a Foxglove client costs localization (issue 22)",
            "",
            f"Command: `flock /work/timing.lock python -m bench.liveview --robots {robots} "
            f"--duration {duration:g}{flags} --write`",
            "",
            f"Machine: {platform.machine()}, {os.cpu_count()} cores, CPython "
            f"{platform.python_version()}. The fleet benchmark's setup (`bench.fleet`: one "
            f"`rlutf serve`, recording {'on' if record else 'off'}, and one load-generator "
            f"process, {robots} robots at 10 Hz, 360-beam scans, {duration:g} s) run three "
            "times: without `--foxglove-port`, with it and no client, and with a Foxglove "
            "WebSocket client (`websockets`, `foxglove.sdk.v1`, in the benchmark's process) "
            "subscribed to every channel for the whole run, at the default "
            "`foxglove_rate_hz` (10). CPU is the service's, per scan sent, over the publishing "
            f"interval. Load average when the run started: {load:.1f}.",
            "",
            "| live view | scans sent | poses | dropped | CPU ms per scan: main / workers "
            "| service CPU ms per scan | latency p50 / p99 ms | CPU stolen, % "
            "| what the client received |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            *rows,
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
