"""``rlutf initialpose|events``: set a robot's pose, watch the fleet's Events."""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from typing import Any

from service.cli.errors import EXIT_FAILURE, EXIT_OK
from service.cli.flags import client, seconds, zenoh_flags
from service.cli.query import (
    OFF_MAP_M,
    check_ids,
    json_flag,
    off_map,
    refused_hint,
    request_flags,
    require_service,
    show_event,
    show_other,
    tenths,
)


def register(sub: Any) -> None:
    """Add ``initialpose`` and ``events`` to the ``rlutf`` subcommands."""
    init = sub.add_parser(
        "initialpose",
        help="set a robot's pose on a map (RViz's 2D Pose Estimate)",
        description="Put an InitialPose on {prefix}/robots/ROBOT/initialpose: the robot's base "
        "is at X, Y (metres) with heading THETA (radians, counter-clockwise from the map's x "
        "axis; --degrees for degrees) on map ID. The service starts tracking it from its next "
        "scan (a lost robot is re-seeded). Then the robot's Events are followed for --wait "
        "seconds: exit 0 when a pose on the map comes, or when the time runs out with no "
        "refusal (a robot not sending scans yet); exit 1 when no service is live or it refuses "
        "the request (map not in the store).",
    )
    request_flags(init, 5.0, "until its first pose on the map")
    init.add_argument(
        "--pose",
        required=True,
        type=_pose,
        metavar="X,Y,THETA",
        help="pose in map coordinates, e.g. --pose -1.5,2.0,0.3 (metres, radians)",
    )
    init.add_argument("--degrees", action="store_true", help="THETA is in degrees")
    init.add_argument(
        "--force",
        action="store_true",
        help=f"put the pose even if it lies more than {OFF_MAP_M:g} m outside the stored map's "
        "free space (by default refused: a pose there is a typo, a unit or a map mix-up)",
    )
    init.set_defaults(func=cmd_initialpose)

    events = sub.add_parser(
        "events",
        help="print a robot's Events (or every robot's and the service's) as they arrive",
        description="Follow {prefix}/robots/ROBOT/events, or without ROBOT every robot's and "
        "the service-wide {prefix}/events, and print each Event as it arrives: local time, "
        "level, robot ('-' for the service), code and message. Ends after --seconds or on "
        "Ctrl-C (exit 0).",
    )
    events.add_argument("robot", nargs="?", help="robot id (default: every robot and the service)")
    events.add_argument(
        "--seconds",
        type=seconds(above=0),
        metavar="S",
        help="stop after S seconds (default: run until Ctrl-C)",
    )
    json_flag(events, "one Event (WIRE.md) per line")
    zenoh_flags(events, client=True)
    events.set_defaults(func=cmd_events)


def _pose(text: str) -> tuple[float, float, float]:
    try:
        x, y, theta = (float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give three numbers X,Y,THETA (metres, radians), e.g. -1.5,2.0,0.3"
        ) from None
    if not all(math.isfinite(v) for v in (x, y, theta)):
        raise argparse.ArgumentTypeError(f"{text!r}: numbers must be finite")
    return x, y, theta


def cmd_initialpose(args: argparse.Namespace) -> int:
    """``rlutf initialpose ROBOT --map ID --pose X,Y,THETA``."""
    from schemas import InitialPose, encode
    from service.cli.present import pose_line
    from service.keys import Keys
    from service.live.queries import put_request

    check_ids("initialpose", robot=args.robot, map=args.map)
    x, y, theta = args.pose
    if args.degrees:
        theta = math.radians(theta)
    request = InitialPose(stamp_ns=time.time_ns(), map_id=args.map, x=x, y=y, theta=theta)
    settings, session = client(args)
    with session:
        require_service(session, settings.prefix, settings.connect)
        if not args.force:
            key = Keys(settings.prefix).map(args.map)
            for reply in session.get(key, timeout=5.0):  # the storage's answer: at once
                why = None if reply.ok is None else off_map(reply.ok.payload.to_bytes(), x, y)
                if why is not None:
                    print(f"rlutf initialpose: refused: {why}", file=sys.stderr)
                    return EXIT_FAILURE
        outcome = put_request(
            session, settings.prefix, args.robot, request, args.wait, show_event(args.json)
        )
    said = f"{args.robot} at x {x:g} m, y {y:g} m, θ {tenths(math.degrees(theta))}° on {args.map}"
    if outcome.result == "refused":
        print(refused_hint("initialpose", args.map, outcome.code), file=sys.stderr)
        return EXIT_FAILURE
    if outcome.result == "done":
        if args.json and outcome.pose is not None:
            print(encode(outcome.pose).decode())
        elif not args.json:
            print(f"initial pose set: {said}")
            if outcome.pose is not None:
                print(pose_line(outcome.pose))
        return EXIT_OK
    if args.wait > 0:
        print(
            f"initial pose put: {said}; no pose within {args.wait:g} s: the robot's next scan "
            f"starts it (is it sending scans? watch with `rlutf events {args.robot}`)",
            file=sys.stderr,
        )
    else:
        print(f"initial pose put: {said}")
    return EXIT_OK


def cmd_events(args: argparse.Namespace) -> int:
    """``rlutf events [ROBOT]``: until ``--seconds`` or Ctrl-C."""
    from service.live.queries import follow_events, live_instances

    if args.robot is not None:
        check_ids("events", robot=args.robot)
    settings, session = client(args)
    stop = threading.Event()
    with session:
        if not live_instances(session, settings.prefix):
            print(
                f"rlutf events: no rlutf service is live on prefix {settings.prefix!r} yet; "
                "waiting for Events anyway (Ctrl-C ends)",
                file=sys.stderr,
                flush=True,
            )
        try:
            follow_events(
                session,
                settings.prefix,
                args.robot,
                show_event(args.json),
                stop,
                args.seconds,
                show_other(),
            )
        except KeyboardInterrupt:
            stop.set()
    return EXIT_OK
