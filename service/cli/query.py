"""``rlutf pose|relocalize|health``: ask a running fleet for poses, relocalize a robot, health."""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any

from service.cli.flags import client, zenoh_flags


def register(sub: Any) -> None:
    """Add ``pose`` and ``health`` to the ``rlutf`` subcommands."""
    pose = sub.add_parser("pose", help="query the latest pose of one robot or all")
    pose.add_argument("robot", nargs="?", default="*", help="robot id (default: all)")
    pose.add_argument("--timeout", type=float, default=3.0)
    zenoh_flags(pose, client=True)
    pose.set_defaults(func=cmd_pose)

    reloc = sub.add_parser(
        "relocalize",
        help="find a robot on a map from its scans (kidnapped or lost robot)",
        description="Put a Relocalize on {prefix}/robots/ROBOT/relocalize: the service forgets "
        "the robot's pose and localizes it globally on map ID from its next scans (and the "
        "odometry between them), then tracks it as usual. Where several places fit the scans "
        "about equally, the poses say lost and carry the hypotheses until one wins. A map no "
        "storage holds gets the Event map_not_found and changes nothing. With --wait, the "
        "robot's Events are printed until it is relocalized (exit 0) or the request fails or "
        "the time runs out (exit 1).",
    )
    reloc.add_argument("robot", help="robot id")
    reloc.add_argument("--map", required=True, metavar="ID", help="map the robot is on")
    reloc.add_argument(
        "--near",
        metavar="X,Y,RADIUS",
        type=_region,
        help="search only within RADIUS metres of (X, Y) in map coordinates (default: the "
        "whole map)",
    )
    reloc.add_argument(
        "--wait",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="follow the robot's events this long (default 10; 0: put and exit)",
    )
    zenoh_flags(reloc, client=True)
    reloc.set_defaults(func=cmd_relocalize)

    health = sub.add_parser("health", help="query instances' health; exit 1 if none answers")
    health.add_argument("--timeout", type=float, default=3.0)
    health.add_argument("--instance", default="*", help="instance name (default: all)")
    zenoh_flags(health, client=True)
    health.set_defaults(func=cmd_health)


def cmd_pose(args: argparse.Namespace) -> int:
    """``rlutf pose [ROBOT]``."""
    from service.live.queries import query_poses

    settings, session = client(args)
    with session:
        return query_poses(session, settings.prefix, args.robot, args.timeout)


def _region(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        x, y, radius = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give three numbers X,Y,RADIUS (metres), e.g. 4.0,2.5,3"
        ) from None
    if not all(math.isfinite(v) for v in (x, y, radius)):
        raise argparse.ArgumentTypeError(f"{text!r}: numbers must be finite")
    if radius <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: RADIUS must be > 0, got {radius:g}")
    return x, y, radius


def cmd_relocalize(args: argparse.Namespace) -> int:
    """``rlutf relocalize ROBOT --map ID [--near X,Y,RADIUS] [--wait SECONDS]``."""
    from schemas import Region, Relocalize, valid_id
    from service.live.queries import request_relocalize

    for what, value in (("robot", args.robot), ("map", args.map)):
        if not valid_id(value):
            print(
                f"rlutf relocalize: invalid {what} id {value!r} (use [A-Za-z0-9_-]{{1,64}})",
                file=sys.stderr,
            )
            return 2
    region = None
    if args.near is not None:
        x, y, radius = args.near
        region = Region(x=x, y=y, radius=radius)
    request = Relocalize(stamp_ns=time.time_ns(), map_id=args.map, region=region)
    settings, session = client(args)
    with session:
        return request_relocalize(session, settings.prefix, args.robot, request, args.wait)


def cmd_health(args: argparse.Namespace) -> int:
    """``rlutf health``: 0 if an instance answers."""
    from service.live.queries import query_health

    settings, session = client(args)
    with session:
        return query_health(session, settings.prefix, args.instance, args.timeout)
