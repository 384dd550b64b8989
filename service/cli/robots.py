"""``rlutf robots``: every robot the live instances hold, as a table or JSON."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from service.cli.flags import EXIT_FAILURE, EXIT_OK, client, zenoh_flags


def register(sub: Any) -> None:
    """Add ``robots`` to the ``rlutf`` subcommands."""
    robots = sub.add_parser(
        "robots",
        help="list the robots every live instance holds; exit 1 if none answers",
        description="Ask every live instance on {prefix}/service/*/robots and print one line per "
        "robot, sorted by robot id: its map, the status and x, y, theta of its latest pose, "
        "the pose's age (seconds since the instance published it, on that instance's clock), "
        "its scan-to-pose latency in milliseconds and the instance that owns it. A robot two "
        "instances answer for (during a handover) is shown once, with the fresher pose. "
        "'-' marks a figure the instance does not have (a pose it was handed, not one it "
        "published). Exit 1 if no instance answers.",
    )
    robots.add_argument(
        "--timeout", type=float, default=3.0, help="seconds to wait for answers (default 3)"
    )
    robots.add_argument(
        "--json", action="store_true", help="print one JSON array of robots instead of a table"
    )
    zenoh_flags(robots, client=True)
    robots.set_defaults(func=cmd_robots)


def cmd_robots(args: argparse.Namespace) -> int:
    """``rlutf robots``: 0 if at least one instance answers."""
    from service.live.robots import fetch_robots, merge_robots, robots_json, robots_table

    settings, session = client(args)
    with session:
        answers = fetch_robots(session, settings.prefix, args.timeout)
    if not answers:
        print("rlutf robots: no instance answered", file=sys.stderr)
        return EXIT_FAILURE
    states = merge_robots(answers)
    print(robots_json(states) if args.json else robots_table(states))
    return EXIT_OK
