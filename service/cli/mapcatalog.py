"""``rlutf map list|remove``: the stored maps with the robots on each, and a deliberate removal."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from service.cli.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, CliError
from service.cli.flags import client


def cmd_catalog(args: argparse.Namespace) -> int:
    """``rlutf map list`` and ``rlutf map remove ID``."""
    from schemas import valid_id
    from service.live.robots import fetch_robots
    from service.maps.catalog import list_maps, remove_map

    if args.map_command == "remove" and not valid_id(args.map_id):
        raise CliError(
            f"invalid map id {args.map_id!r}: use 1 to 64 of A-Z a-z 0-9 _ -", EXIT_USAGE
        )
    settings, session = client(args)
    with session:
        on = _robots_on(fetch_robots(session, settings.prefix, args.timeout))
        stored = list_maps(session, settings.prefix, args.timeout)
        if args.map_command == "list":
            shown = _print_maps(stored, on, args.json)
            hidden = _not_served(session, settings.prefix, stored, args.timeout)
            for line in hidden:
                print(line, file=sys.stderr)
            if stored or hidden:
                return EXIT_FAILURE if hidden else shown
            return _none_stored(session, settings.prefix)
        if args.map_id not in {m.map_id for m in stored}:
            raise CliError(
                f"no storage holds map {args.map_id!r} (`rlutf map list` shows the stored maps)"
            )
        robots = on.get(args.map_id, [])
        if robots and not args.force:
            raise CliError(
                f"robots are on map {args.map_id!r}: {', '.join(robots)}; they would keep their "
                "service's copy until it restarts. Remove it anyway with --force"
            )
        if not remove_map(session, settings.prefix, args.map_id, args.timeout):
            raise CliError(
                f"a storage still answers for map {args.map_id!r} after {args.timeout:g} s: it "
                "does not honour deletes (zenohd's storage manager?); remove it there"
            )
    print(f"removed map {args.map_id} from {settings.prefix}/maps/{args.map_id}")
    return EXIT_OK


def _robots_on(answers: list[Any]) -> dict[str, list[str]]:
    """The robots on each map, by map id: those with a pose on it, and those placed on it (an
    initial pose or a relocalize) that have no pose yet, which the service holds on that map all
    the same (waiting for their first scan, or for scans with enough returns): counted with a
    pose only, a map a robot had just been placed on was removed without ``--force``."""
    from service.live.robots import merge_robots, merge_waiting

    on: dict[str, list[str]] = {}
    for state in merge_robots(answers):
        on.setdefault(state.map_id, []).append(state.robot_id)
    for waiting in merge_waiting(answers):
        if waiting.map_id is not None:
            on.setdefault(waiting.map_id, []).append(waiting.robot_id)
    return {map_id: sorted(robots) for map_id, robots in on.items()}


def _print_maps(stored: list[Any], on: dict[str, list[str]], as_json: bool) -> int:
    from service.cli.present import table

    if as_json:
        rows = [
            {
                "map_id": m.map_id,
                "version": m.version,
                "size_bytes": m.size_bytes,
                "extent_m": None if m.extent is None else list(m.extent),
                "robots": on.get(m.map_id, []),
            }
            for m in stored
        ]
        print(json.dumps(rows))
    else:
        print(
            table(
                ("map", "version", "size", "extent m", "robots"),
                (
                    [
                        m.map_id,
                        "-" if m.version is None else str(m.version),
                        _size(m.size_bytes),
                        "-" if m.extent is None else f"{m.extent[0]:.1f} x {m.extent[1]:.1f}",
                        _robots(on.get(m.map_id, [])),
                    ]
                    for m in stored
                ),
                {1, 2, 3},
            )
        )
    return EXIT_OK


def _not_served(session: Any, prefix: str, stored: list[Any], timeout: float) -> list[str]:
    """A line for each map a store holds but does not serve: its file was changed or removed on
    disk (the store said which with ``invalid_map``). Before, such a map was not listed at all,
    or, alone, "no maps stored yet" (exit 0) was printed."""
    from service.keys import Keys
    from service.maps.store import stored_versions

    served = {m.map_id for m in stored}
    held = stored_versions(session, Keys(prefix), min(timeout, 2.0))
    return [
        f"map {a.map_id} version {a.version}: held by the map store but not served, its file "
        "changed or removed on disk (`rlutf events` says which); put it again: "
        f"rlutf map put FILE --id {a.map_id}"
        for a in sorted(held.values(), key=lambda a: a.map_id)
        if a.version is not None and not a.removed and a.map_id not in served
    ]


def _none_stored(session: Any, prefix: str) -> int:
    """No storage answered with a map. A store with no map answers nothing, as no store does:
    with a service live (whose embedded store is empty, on a first day), an empty list (exit 0)
    and how to put one; with none, exit 1 (the first ``map list`` of a new site said "no storage
    answered", exit 1, as if the service were down)."""
    from service.live.queries import live_instances

    if live_instances(session, prefix):
        print(
            "no maps stored yet: put one with `rlutf map put FILE` or `rlutf map import "
            "site.yaml --put`",
            file=sys.stderr,
        )
        return EXIT_OK
    print(
        "rlutf map list: no storage answered with a map, and no rlutf service is live on "
        f"prefix {prefix!r} (is `rlutf serve` running?)",
        file=sys.stderr,
    )
    return EXIT_FAILURE


def _size(n: int) -> str:
    if n < 1024:
        return f"{n} B"
    if n < 1024 * 1024:
        return f"{n / 1024:.1f} KB"
    return f"{n / 1024 / 1024:.1f} MB"


def _robots(ids: list[str], most: int = 5) -> str:
    if not ids:
        return "-"
    shown = ", ".join(ids[:most])
    return f"{shown} and {len(ids) - most} more" if len(ids) > most else shown
