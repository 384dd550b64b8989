"""``rlutf robots``: every robot the live instances hold, as a table or JSON."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from service.cli.errors import EXIT_FAILURE, EXIT_OK, unanswered_hint
from service.cli.flags import client, number, timeout_flag, zenoh_flags
from service.cli.present import SILENT_AFTER_S


def register(sub: Any) -> None:
    """Add ``robots`` to the ``rlutf`` subcommands."""
    robots = sub.add_parser(
        "robots",
        help="list the robots every live instance holds; exit 1 if none answers",
        description="Ask every live instance on {prefix}/service/*/robots and print one line per "
        "robot, sorted by robot id: its map, the status and x, y (metres), heading (degrees) of "
        "its latest pose, the pose's 1-sigma uncertainty (position in centimetres, heading in "
        "degrees), the pose's age (since the instance published it, on that instance's clock), "
        "its scan-to-pose latency in milliseconds and the instance that owns it. A robot with "
        "no pose for over --silent seconds shows as 'silent (last status)'. Robots that send "
        "scans but have no pose yet (no initial pose, or their map not loaded) follow with "
        "status 'waiting', and robots given an initial pose that have sent no scan since with "
        "'no scan yet'. A robot two instances answer for (during a handover) is shown once, "
        "with the fresher pose. '-' marks a figure the instance does not have. Exit 1 if no "
        "instance answers.",
    )
    timeout_flag(robots)
    robots.add_argument(
        "--silent",
        type=number(above=0),
        default=SILENT_AFTER_S,
        metavar="SECONDS",
        help=f"mark robots with no pose for this long as silent (default {SILENT_AFTER_S:g})",
    )
    robots.add_argument(
        "--json",
        action="store_true",
        help="print one JSON array of robots instead of a table (each with 'silent'; waiting "
        "robots have status 'waiting', a reason (not_initialized, map_not_found, no_scan_yet, "
        "no_returns) "
        "and no pose)",
    )
    zenoh_flags(robots, client=True)
    robots.set_defaults(func=cmd_robots)


def cmd_robots(args: argparse.Namespace) -> int:
    """``rlutf robots``: 0 if at least one instance answers."""
    from service.cli.present import robots_table
    from service.live.robots import fetch_robots, merge_robots, merge_waiting

    settings, session = client(args)
    with session:
        answers = fetch_robots(session, settings.prefix, args.timeout)
    if not answers:
        print(
            f"rlutf robots: no instance answered on prefix {settings.prefix!r} within "
            f"{args.timeout:g} s; {unanswered_hint(args)}",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    states = merge_robots(answers)
    waiting = merge_waiting(answers)
    if args.json:
        rows: list[dict[str, Any]] = [
            {
                **s.model_dump(mode="json"),
                "silent": s.age_s is not None and s.age_s > args.silent,
            }
            for s in states
        ]
        rows += [
            {
                "robot_id": w.robot_id,
                "map_id": w.map_id,
                "status": "waiting",
                "reason": w.reason,
                "age_s": w.age_s,
                "owner": w.owner,
                "silent": w.age_s > args.silent,
            }
            for w in waiting
        ]
        print(json.dumps(rows))
    elif not states and not waiting:  # a header alone read as a table cut off
        names = ", ".join(sorted({a.instance for a in answers}))
        print(
            f"no robots: {len(answers)} instance(s) answered ({names}) and hold none; a robot is "
            "held once its first scan, odometry or initial pose reaches the service"
        )
    else:
        print(robots_table(states, waiting, args.silent))
    return EXIT_OK
