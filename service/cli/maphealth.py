"""``rlutf map health ID``: where the fleet's scans disagree with a map (WIRE.md MapHealth).

The current MapHealth of a map from the service (a get on ``{prefix}/maphealth/{map_id}``) or,
with ``--log``, the last one recorded in logs (a live run's, or the output of ``rlutf
replay``). Prints one line per change; ``--json`` prints the message; ``--png`` draws the map
(from the store, or from the logs) with the changes over it.
"""

from __future__ import annotations

import argparse
import json
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from service.cli.flags import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    client,
    timeout_flag,
    writable,
    zenoh_flags,
)
from service.keys import printable


def register(msub: Any) -> None:
    """Add ``health`` to the ``rlutf map`` actions."""
    p = msub.add_parser(
        "health",
        help="where the fleet's scans disagree with a map",
        description="Print the map's MapHealth: the places where robots consistently see "
        "something the map lacks (added) or see through its walls (removed).",
    )
    p.add_argument("map_id", help="the map's id")
    p.add_argument("--json", action="store_true", help="print the MapHealth message as JSON")
    p.add_argument("--png", type=Path, help="draw the map with the changes over it")
    p.add_argument(
        "--log",
        type=Path,
        nargs="+",
        help="read the last MapHealth recorded in these logs (MCAP files, or folders of them)",
    )
    timeout_flag(p, what="the service's MapHealth and map")
    zenoh_flags(p, client=True)
    p.set_defaults(func=cmd_health)


def cmd_health(args: argparse.Namespace) -> int:
    """``rlutf map health``."""
    from service.logs.mcapread import LogError

    if args.png is not None:
        writable(args.png, "--png")  # before any work, as every output path
    try:
        found = _from_logs(args.log, args.map_id) if args.log else _from_service(args)
    except LogError as err:
        print(f"rlutf map health: {err}", file=sys.stderr)
        return EXIT_USAGE
    if found is None or isinstance(found, str):
        where = f"no MapHealth recorded in the logs for map {args.map_id!r}" if args.log else found
        print(f"rlutf map health: {where}", file=sys.stderr)
        return EXIT_FAILURE
    health, world = found
    if args.json:
        print(json.dumps(health))
    else:
        print(summary(health))
    if args.png is not None:
        if world is None:
            print(f"rlutf map health: map {args.map_id!r} not found to draw", file=sys.stderr)
            return EXIT_FAILURE
        from service.maps.mapimport import render_map

        title = f"{args.map_id} v{health['version']}: {len(health['changes'])} changes"
        render_map(world, args.png, title=title, changes=health["changes"])
        print(f"wrote {args.png}", file=sys.stderr if args.json else sys.stdout)
    return EXIT_OK


def _from_service(args: argparse.Namespace) -> tuple[dict[str, Any], Any] | str:
    """The map's MapHealth and (for ``--png``) its map; else why there is none.

    A live service answers only for a map version it has counted scans of: before the first
    well-localized scan on it (a new site, a new version put, robots not yet on it), nothing
    answers, as when no service runs. Which one it is, is said (it read "no service answered"
    while the service was running, and an operator went looking for a service that was up)."""
    from service.keys import Keys
    from service.live.queries import live_instances

    settings, session = client(args)
    keys = Keys(settings.prefix)
    from schemas import Map, MapHealth

    with session:
        health = _first(session.get(keys.maphealth(args.map_id), timeout=args.timeout), MapHealth)
        world = None
        if health is not None and args.png is not None:
            world = _first(session.get(keys.map(args.map_id), timeout=args.timeout), Map)
        live = health is None and bool(live_instances(session, settings.prefix))
        stored = not live or any(  # a mistyped id is no map waiting for its first scans
            reply.ok is not None
            for reply in session.get(keys.map(args.map_id), timeout=args.timeout)
        )
    if health is not None:
        return health, world
    if not stored:
        return (
            f"no storage holds map {args.map_id!r}, so it has no MapHealth (the service is "
            "live); `rlutf map list` shows the stored maps"
        )
    if live:
        return (
            f"no MapHealth for map {args.map_id!r} yet: the service is live but has counted no "
            "scan of a well-localized robot on the map's current version (a new version starts "
            "afresh); `rlutf robots` shows which robots are on which map"
        )
    return (
        f"no service answered for map {args.map_id!r}, and no rlutf service is live on prefix "
        f"{settings.prefix!r} (is `rlutf serve` running? use -e/--connect)"
    )


def _first(replies: Any, model: Any) -> dict[str, Any] | None:
    """The first answer that is a ``model`` message, as JSON data; ``None`` if none is (any
    client may answer on these keys: what is no such message is said and skipped)."""
    from schemas import SchemaError, decode

    for reply in replies:
        if reply.ok is not None:
            payload = reply.ok.payload.to_bytes()
            try:
                decode(model, payload, max_bytes=len(payload))
            except SchemaError as err:
                key = printable(str(reply.ok.key_expr))
                print(f"rlutf map health: the answer on {key} is no {model.__name__}: {err}",
                      file=sys.stderr)  # fmt: skip
                continue
            data = json.loads(payload)
            return data if isinstance(data, dict) else None
    return None


def _from_logs(paths: list[Path], map_id: str) -> tuple[dict[str, Any], Any] | None:
    from contextlib import ExitStack

    from service.cli.present import unfinished
    from service.logs.mcapread import LogFile, merged_messages
    from service.logs.runs import log_files

    health = world = None
    with ExitStack() as stack:
        files = log_files(paths)
        unfinished("map health", paths, files, "not read")
        logs = [stack.enter_context(LogFile(p)) for p in files]
        for rec in merged_messages(logs, {"rlutf.MapHealth", "rlutf.Map"}):
            data = json.loads(rec.payload)
            if not isinstance(data, dict) or data.get("map_id") != map_id:
                continue
            if rec.schema_name == "rlutf.MapHealth":
                health = data
            elif world is None or data.get("version", 0) >= world.get("version", 0):
                world = data
    return None if health is None else (health, world)


def _time(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).strftime("%Y-%m-%d %H:%M:%S")


def summary(health: dict[str, Any]) -> str:
    """A MapHealth as text: a head line, then one line per change."""
    lines = [
        f"map {health['map_id']} v{health['version']}: {health['scans']} scans from "
        f"{health['robots']} robots, {_time(health['since_ns'])} to "
        f"{_time(health['stamp_ns'])} UTC; {len(health['changes'])} changes"
    ]
    import shapely.geometry

    for c in health["changes"]:
        g = shapely.geometry.shape(c["geometry"])
        x, y = g.centroid.x, g.centroid.y
        size = f"{g.area:.2f} m2" if c["kind"] == "added" else f"{g.length:.2f} m of wall"
        lines.append(
            f"  {c['kind']:<7} at ({x:.2f}, {y:.2f}): {size}, confidence {c['confidence']:.2f}, "
            f"{c['evidence']} returns from {c['robots']} robots, {_time(c['first_ns'])} to "
            f"{_time(c['last_ns'])}"
        )
    return "\n".join(lines)
