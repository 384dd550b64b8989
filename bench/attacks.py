"""The attack classes of :mod:`bench.adversarial`: what an adversarial client puts on the bus.

Each class is a function ``attack(ctx)`` that runs in the attacking process while three good
robots drive: it puts its messages (as a client of the service's router would) and returns how
many it put. :data:`CLASSES` names them; ``mixed`` interleaves the cheap ones at a fixed rate.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from typing import Any

T_FAR = 2**62  # a stamp ~146 years ahead


@dataclass
class Context:
    """What an attack needs.

    Attributes:
        session: the attacker's Zenoh session (a client of the service's router).
        service_pid: the service's process id (for ``kill-worker``).
        good: ids of the good robots.
        truth: each good robot's start pose (a place on the map ``bench``).
        scale: 1.0 for the full campaign, smaller for ``--quick``.
        duration: seconds the attack may take (``mixed`` runs this long).
        notes: what the attack wants reported beside its figures.
        extra: figures of the attack's own that its targets read.
    """

    session: Any
    service_pid: int
    good: list[str]
    truth: dict[str, tuple[float, float, float]]
    scale: float = 1.0
    duration: float = 10.0
    notes: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def count(self, full: int) -> int:
        """``full`` scaled for the mode, at least 1."""
        return max(1, int(full * self.scale))


def _now() -> int:
    return time.time_ns()


def _scan(ranges: list[float | None], range_max: float = 30.0, **extra: Any) -> bytes:
    n = len(ranges)
    body = {
        "stamp_ns": _now(),
        "angle_min": -math.pi,
        "angle_increment": 2 * math.pi / n,
        "range_min": 0.05,
        "range_max": range_max,
        "ranges": ranges,
        **extra,
    }
    return json.dumps(body).encode()


def _odom(x: float = 0.0, y: float = 0.0, theta: float = 0.0, stamp: int | None = None) -> bytes:
    return json.dumps({"stamp_ns": stamp or _now(), "x": x, "y": y, "theta": theta}).encode()


def _initialpose(map_id: str, x: float, y: float, theta: float = 0.0) -> bytes:
    body = {"stamp_ns": _now(), "map_id": map_id, "x": x, "y": y, "theta": theta}
    return json.dumps(body).encode()


def _square_map(map_id: str, side: float) -> bytes:
    ring = [[0.0, 0.0], [side, 0.0], [side, side], [0.0, side], [0.0, 0.0]]
    geometry = {"type": "Polygon", "coordinates": [ring]}
    return json.dumps({"map_id": map_id, "version": 1, "geometry": geometry}).encode()


def _round_geometry(vertices: int, radius: float, digits: int = 6) -> dict[str, Any]:
    """A round room of ``vertices`` vertices, its coordinates rounded to ``digits``."""
    ring = [
        [
            round(radius + radius * math.cos(2 * math.pi * k / vertices), digits),
            round(radius + radius * math.sin(2 * math.pi * k / vertices), digits),
        ]
        for k in range(vertices)
    ]
    return {"type": "Polygon", "coordinates": [[*ring, ring[0]]]}


def _round_map(map_id: str, vertices: int, radius: float = 20.0) -> bytes:
    geometry = _round_geometry(vertices, radius)
    return json.dumps({"map_id": map_id, "version": 1, "geometry": geometry}).encode()


def _placed(ctx: Context, robot: str, map_id: str, x: float, y: float) -> None:
    """An attacker robot with odometry and an initial pose (so its scans are searched)."""
    s = ctx.session
    s.put(f"rlutf/robots/{robot}/odom", _odom())
    s.put(f"rlutf/robots/{robot}/initialpose", _initialpose(map_id, x, y))
    time.sleep(0.2)


# --------------------------------------------------------------------------------- classes
def burst_good(ctx: Context) -> int:
    """1,000 malformed payloads at once on a good robot's scan key."""
    key = f"rlutf/robots/{ctx.good[0]}/scan"
    n = ctx.count(1000)
    for i in range(n):
        ctx.session.put(key, b'{"stamp_ns": ' + str(i).encode() + b", not json")
    return n


def burst_fresh(ctx: Context) -> int:
    """1,000 malformed payloads at once, each on a fresh robot id."""
    n = ctx.count(1000)
    for i in range(n):
        ctx.session.put(f"rlutf/robots/fresh{i}/scan", b"[1, 2")
    return n


def map_2km(ctx: Context) -> int:
    """A 144-byte map 2 km square, and a robot placed on it that sends scans."""
    ctx.session.put("rlutf/maps/huge2km", _square_map("huge2km", 2000.0))
    _placed(ctx, "atk-huge", "huge2km", 1000.0, 1000.0)
    for _ in range(5):
        ctx.session.put("rlutf/robots/atk-huge/scan", _scan([10.0] * 360))
        time.sleep(0.1)
    return 8


def map_40k(ctx: Context) -> int:
    """A map of 40,000 vertices, and a robot placed on it that sends scans."""
    n = ctx.count(40_000)
    ctx.session.put("rlutf/maps/round40k", _round_map("round40k", n))
    _placed(ctx, "atk-round", "round40k", 20.0, 20.0)
    for _ in range(5):
        ctx.session.put("rlutf/robots/atk-round/scan", _scan([20.0] * 360))
        time.sleep(0.1)
    return 8


def map_flood(ctx: Context) -> int:
    """A 5 MB map put again and again, each time one version newer, for the duration."""
    geometry = json.dumps(_round_geometry(ctx.count(200_000), 40.0, digits=4)).encode()
    loaded: list[int] = []
    found = re.compile(r"map flood version (\d+) loaded")

    def on_event(sample: Any) -> None:
        hit = found.search(json.loads(sample.payload.to_bytes()).get("message", ""))
        if hit:
            loaded.append(int(hit.group(1)))

    sub = ctx.session.declare_subscriber("rlutf/events", on_event)
    start = time.monotonic()
    n = 0
    while time.monotonic() - start < 0.6 * ctx.duration:
        n += 1
        body = b'{"map_id": "flood", "version": %d, "geometry": %s}' % (n, geometry)
        ctx.session.put("rlutf/maps/flood", body)
        time.sleep(0.02)
    end = time.monotonic() + 0.4 * ctx.duration + 20.0

    def stored_version() -> int:
        replies = ctx.session.get("rlutf/maps/flood", timeout=10.0)
        versions = [json.loads(r.ok.payload.to_bytes())["version"] for r in replies if r.ok]
        return max(versions, default=0)

    # The store too may drop the last puts (with an Event that asks for them again): once it
    # holds the same version for a second, the service must end on that one.
    stored, previous = stored_version(), -1
    while stored != previous and time.monotonic() < end:
        time.sleep(1.0)
        stored, previous = stored_version(), stored
    while (not loaded or loaded[-1] != stored) and time.monotonic() < end:
        time.sleep(0.1)
    sub.undeclare()
    last = loaded[-1] if loaded else 0
    ctx.extra["last_loaded"] = last
    ctx.extra["stored"] = stored
    ctx.notes.append(
        f"{n} puts of {len(body) / 1e6:.1f} MB, {len(loaded)} loaded, the last version {last}, "
        f"the store's {stored}"
    )
    return n


def scan_far(ctx: Context) -> int:
    """After a valid initial pose on the good robots' map, scans whose ranges are all 1e5 m."""
    x, y, _ = ctx.truth[ctx.good[0]]
    _placed(ctx, "atk-far", "bench", x, y)
    for _ in range(3):
        ctx.session.put("rlutf/robots/atk-far/scan", _scan([1e5] * 360, range_max=1e6))
        time.sleep(0.2)
    return 5


def _workers(pid: int) -> list[int]:
    """The service's worker processes (spawned children running ``spawn_main``)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                parent = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                cmdline = f.read()
        except OSError:
            continue
        if parent == pid and b"spawn_main" in cmdline:
            found.append(int(entry))
    return sorted(found)


def kill_worker(ctx: Context) -> int:
    """``kill -9`` of one of the service's worker processes, as the OOM killer would."""
    workers = _workers(ctx.service_pid)
    if not workers:
        ctx.notes.append("no worker process found")
        return 0
    os.kill(workers[0], signal.SIGKILL)
    ctx.notes.append(f"killed worker {workers[0]} of {len(workers)}")
    return 1


def forged_pose(ctx: Context) -> int:
    """A far-future pose 4 m off on a good robot's pose key, and a fake instance token."""
    robot = ctx.good[0]
    x, y, theta = ctx.truth[robot]
    pose = {
        "stamp_ns": T_FAR,
        "robot_id": robot,
        "map_id": "bench",
        "x": x + 4.0,
        "y": y,
        "theta": theta,
        "status": "tracking",
        "discrepancy": 0.0,
        "iterations": 0,
    }
    ctx.session.put(f"rlutf/robots/{robot}/pose", json.dumps(pose).encode())
    token = ctx.session.liveliness().declare_token("rlutf/service/x")
    time.sleep(min(6.0, ctx.duration / 2))
    token.undeclare()
    return 2


def many_ids(ctx: Context) -> int:
    """One odometry reading from each of 100,000 robot ids."""
    n = ctx.count(100_000)
    body = _odom()
    for i in range(n):
        ctx.session.put(f"rlutf/robots/id{i}/odom", body)
    return n


def _extreme_payloads(robot: str) -> Iterator[tuple[str, bytes]]:
    k = f"rlutf/robots/{robot}"
    yield f"{k}/scan", _scan([1e15] * 360)
    yield f"{k}/scan", _scan([3.0] * 360, angle_increment=5e-324)
    yield f"{k}/scan", _scan([3.0] * 360, angle_min=1e308)
    yield f"{k}/scan", _scan([3.0] * 360, sensor_offset={"x": 1e308, "y": 0, "theta": 0})
    yield f"{k}/scan", _scan([3.0] * 360, range_max=1e308)
    yield f"{k}/scan", _scan([3.0] * 8192)
    yield f"{k}/odom", _odom(1e308, -1e308, 1e308)
    yield f"{k}/odom", _odom(1e15, 0.0, 0.0, stamp=2**63 - 1)
    yield f"{k}/initialpose", _initialpose("bench", 1e308, 1e308, 1e308)
    body = {"stamp_ns": _now(), "map_id": "bench", "region": {"x": 0, "y": 0, "radius": 1e308}}
    yield f"{k}/relocalize", json.dumps(body).encode()


def extreme(ctx: Context) -> int:
    """Schema-valid extreme numbers (ranges 1e15, increment 5e-324, poses at 1e308, ...)."""
    x, y, _ = ctx.truth[ctx.good[0]]
    _placed(ctx, "atk-extreme", "bench", x, y)
    n = 0
    for _ in range(ctx.count(5)):
        for key, payload in _extreme_payloads("atk-extreme"):
            ctx.session.put(key, payload)
            n += 1
        time.sleep(0.1)
    return n


def _odd_keys(robot: str) -> list[str]:
    return [
        f"rlutf/robots/{robot}/scan/x",
        "rlutf/robots/atk/scan/x/y",
        "rlutf/robots/atk",
        "rlutf/robots/atk/scans",
        "rlutf/maps/a/b",
        "rlutf/foo",
        "rlutf/service/x/health",
        "rlutf/robots/atk\nforged log line/scan",
    ]


def extra_levels(ctx: Context) -> int:
    """Puts on keys with extra levels, unknown leaves and other ``rlutf/**`` keys."""
    n = 0
    keys = _odd_keys(ctx.good[0])
    for _ in range(ctx.count(100)):
        for key in keys:
            try:
                ctx.session.put(key, _odom())
            except Exception:  # zenoh refuses some keys itself: nothing reaches the service
                continue
            n += 1
    return n


def deletes(ctx: Context) -> int:
    """DELETEs on robot keys (a good robot's included) and on map keys (the good robots')."""
    keys = [
        f"rlutf/robots/{ctx.good[0]}/scan",
        f"rlutf/robots/{ctx.good[0]}/pose",
        "rlutf/robots/atk/odom",
        "rlutf/maps/bench",
        "rlutf/maps/nosuchmap",
    ]
    n = 0
    for _ in range(ctx.count(100)):
        for key in keys:
            ctx.session.delete(key)
            n += 1
    return n


def _mixed_stream(ctx: Context) -> Iterator[Callable[[], None]]:
    """Single messages of every cheap class, in turn (then again, forever)."""
    s = ctx.session
    good = ctx.good[0]
    i = 0
    odd = _odd_keys(good)
    x, y, _ = ctx.truth[good]
    yield lambda: _placed(ctx, "atk-mix", "bench", x, y)
    yield lambda: s.put("rlutf/maps/huge2km", _square_map("huge2km", 2000.0))
    yield lambda: s.put("rlutf/maps/round40k", _round_map("round40k", ctx.count(40_000)))
    while True:
        i += 1
        yield lambda: s.put(f"rlutf/robots/{good}/scan", b"{broken")
        yield partial(s.put, f"rlutf/robots/mixfresh{i}/scan", b"[1, 2")
        yield partial(s.put, f"rlutf/robots/mixid{i}/odom", _odom())
        yield lambda: s.put("rlutf/robots/atk-mix/scan", _scan([1e5] * 360, range_max=1e6))
        for key, payload in _extreme_payloads("atk-mix"):
            yield partial(s.put, key, payload)
        for key in odd[:-1]:
            yield partial(s.put, key, _odom())
        yield lambda: s.delete("rlutf/robots/atk-mix/scan")
        yield lambda: s.delete("rlutf/maps/nosuchmap")


def mixed(ctx: Context, rate: float = 80.0) -> int:
    """Every cheap class interleaved at ``rate`` messages per second for the duration."""
    stream = _mixed_stream(ctx)
    start = time.monotonic()
    n = 0
    while time.monotonic() - start < ctx.duration:
        delay = start + n / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        next(stream)()
        n += 1
    return n


def none(ctx: Context) -> int:
    """No attack: the reference run."""
    return 0


CLASSES: dict[str, Callable[[Context], int]] = {
    "none": none,
    "burst-good": burst_good,
    "burst-fresh": burst_fresh,
    "map-2km": map_2km,
    "map-40k": map_40k,
    "map-flood": map_flood,
    "scan-1e5": scan_far,
    "kill-worker": kill_worker,
    "forged-pose": forged_pose,
    "many-ids": many_ids,
    "extreme": extreme,
    "extra-levels": extra_levels,
    "deletes": deletes,
    "mixed": mixed,
}
"""Every attack class, by name, in the order the campaign runs them."""
