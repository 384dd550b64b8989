"""``rlutf pose|relocalize|health``: ask a running fleet for poses, relocalize a robot, health."""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from typing import Any

from schemas import Event, EventCode, encode
from service.cli.errors import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, CliError, unanswered_hint
from service.cli.flags import client, seconds, timeout_flag, zenoh_flags


def register(sub: Any) -> None:
    """Add ``pose``, ``relocalize`` and ``health`` to the ``rlutf`` subcommands."""
    pose = sub.add_parser(
        "pose",
        help="query the latest pose of one robot or all",
        description="Print the latest pose of each robot the live instances hold: position in "
        "metres, heading and its 1-sigma in degrees, position 1-sigma in centimetres, the "
        "scan's age. Exit 1 if no pose answers.",
    )
    pose.add_argument("robot", nargs="?", default="*", help="robot id (default: all)")
    timeout_flag(pose, what="the poses")
    json_flag(pose, "one PoseEstimate (WIRE.md) per line")
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
    request_flags(reloc, 10.0, "until it is relocalized")
    reloc.add_argument(
        "--near",
        metavar="X,Y,RADIUS",
        type=_region,
        help="search only within RADIUS metres of (X, Y) in map coordinates (default: the "
        "whole map)",
    )
    reloc.set_defaults(func=cmd_relocalize)

    health = sub.add_parser(
        "health",
        help="query instances' health; exit 1 if none answers",
        description="One line per live instance: ready, uptime, robots, message counters and "
        "the scan-to-pose latency percentiles. --json prints every figure.",
    )
    timeout_flag(health)
    health.add_argument("--instance", default="*", help="instance name (default *: all)")
    json_flag(health, "one Health (WIRE.md) per line")
    zenoh_flags(health, client=True)
    health.set_defaults(func=cmd_health)


def request_flags(p: argparse.ArgumentParser, wait: float, until: str) -> None:
    """The arguments of a request about one robot: ROBOT, ``--map``, ``--wait``, ``--json`` and
    the zenoh flags."""
    p.add_argument("robot", help="robot id")
    p.add_argument("--map", required=True, metavar="ID", help="map the robot is on")
    p.add_argument(
        "--wait",
        type=seconds(minimum=0),
        default=wait,
        metavar="SECONDS",
        help=f"follow the robot's events {until}, at most this long (default {wait:g}; 0: put "
        "and exit)",
    )
    json_flag(p, "the robot's Events as JSON, one per line")
    zenoh_flags(p, client=True)


def json_flag(p: argparse.ArgumentParser, what: str) -> None:
    """Add ``--json`` (print ``what`` instead of the readable text)."""
    p.add_argument("--json", action="store_true", help=f"print {what} instead of text")


def check_ids(command: str, **ids: str) -> None:
    """Refuse an id that cannot be a key (before any connection).

    Raises:
        CliError: naming the argument and the pattern.
    """
    from schemas import valid_id

    for what, value in ids.items():
        if not valid_id(value):
            raise CliError(
                f"invalid {what} id {value!r}: use 1 to 64 of A-Z a-z 0-9 _ -", EXIT_USAGE
            )


def cmd_pose(args: argparse.Namespace) -> int:
    """``rlutf pose [ROBOT]``."""
    from service.cli.present import poses_table
    from service.live.queries import fetch_poses

    if args.robot != "*":
        check_ids("pose", robot=args.robot)
    settings, session = client(args)
    with session:
        poses, bad = fetch_poses(session, settings.prefix, args.robot, args.timeout)
    for key in bad:
        print(f"rlutf pose: undecodable answer on {key}, skipped", file=sys.stderr)
    if not poses:
        whom = "no robot has a pose" if args.robot == "*" else f"no pose for {args.robot}"
        print(
            f"rlutf pose: {whom} (within {args.timeout:g} s); `rlutf robots` lists the robots "
            "and those waiting for a pose, with why",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    if args.json:
        for p in poses:
            print(encode(p).decode())
    else:
        print(poses_table(poses))
    return EXIT_OK


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


def show_event(as_json: bool) -> Any:
    """A callback that prints each Event followed, as JSON or as a line."""
    from service.cli.present import event_line

    def show(robot: str | None, ev: Event) -> None:
        line = encode(ev).decode() if as_json else event_line(robot, ev)
        print(line, flush=True)

    return show


#: Seconds between two lines about payloads on the Event keys that are not Events.
OTHER_EVERY_S = 5.0


def show_other(clock: Any = None) -> Any:
    """A callback that says on stderr, at most once every :data:`OTHER_EVERY_S`, that something
    that is not an Event was put on an Event key (another tool, a broken client): silently
    skipped, an operator watching would not know it is there."""
    now = clock or time.monotonic
    last = [-math.inf]
    skipped = [0]
    lock = threading.Lock()  # Zenoh calls it from its threads: one line per period, not two

    def show(key: str, size: int, why: str) -> None:
        with lock:
            if now() - last[0] < OTHER_EVERY_S:
                skipped[0] += 1
                return
            more = f" (and {skipped[0]} more since the last such line)" if skipped[0] else ""
            last[0], skipped[0] = now(), 0
        from service.keys import printable

        brief = why if len(why) <= 160 else why[:157] + "..."
        line = f"rlutf events: {key}: not an Event ({size} bytes: {brief}){more}"
        print(printable(line, limit=len(line)), file=sys.stderr)

    return show


def require_service(session: Any, prefix: str, endpoints: list[str]) -> None:
    """Refuse to go on when no instance of the service is live.

    Raises:
        CliError: no liveliness token on ``{prefix}/service/*``.
    """
    from service.cli.errors import UNREACHABLE_HINT
    from service.live.queries import live_instances

    if not live_instances(session, prefix):
        raise CliError(
            f"no rlutf service is live on prefix {prefix!r} at {', '.join(endpoints)} (or it "
            f"is still starting): {UNREACHABLE_HINT}; --prefix if it runs with another"
        )


#: A pose farther than this outside the stored map's free space is refused, metres. Nearer, the
#: robot's first scan corrects it (a click into a wall, a rough guess by a door).
OFF_MAP_M = 1.0


def off_map(
    payload: bytes,
    x: float,
    y: float,
    radius: float = 0.0,
    fix: str = "--force puts the pose anyway",
) -> str | None:
    """Why ``(x, y)`` (or every point of the circle of ``radius`` around it) cannot be on the
    stored map ``payload`` (a Map message): farther than :data:`OFF_MAP_M` outside its free
    space; ``None`` when it may be (or the payload is not a map this check can read: the service
    then says what is wrong with it). ``fix`` ends the message."""
    import shapely
    from shapely.geometry import shape

    from schemas import Map, SchemaError, decode

    try:
        world = decode(Map, payload, max_bytes=len(payload))
        free = shape(world.geometry.model_dump())
    except (SchemaError, ValueError, TypeError, AttributeError):
        return None
    point = shapely.Point(x, y)
    away = float(free.distance(point)) - radius
    if free.is_empty or away <= OFF_MAP_M:
        return None
    x0, y0, x1, y1 = free.bounds
    what = f"({x:g}, {y:g})" if radius <= 0 else f"the circle of {radius:g} m around ({x:g}, {y:g})"
    return (
        f"{what} is {tenths(away)} m outside the free space of map {world.map_id!r} "
        f"(version {world.version}: x {x0:.1f} to {x1:.1f} m, y {y0:.1f} to {y1:.1f} m); is the "
        "pose in that map's coordinates, in metres? `rlutf map show "
        f"{world.map_id} --out map.png` draws it; {fix}"
    )


def tenths(value: float) -> str:
    """A number to a tenth, or, past a million, as ``1e+300`` (not its 300 digits)."""
    return f"{value:.1f}" if abs(value) < 1e6 else f"{value:.3g}"


def cmd_relocalize(args: argparse.Namespace) -> int:
    """``rlutf relocalize ROBOT --map ID [--near X,Y,RADIUS] [--wait SECONDS]``."""
    from schemas import Region, Relocalize
    from service.cli.present import pose_line
    from service.live.queries import put_request

    check_ids("relocalize", robot=args.robot, map=args.map)
    region = None
    if args.near is not None:
        x, y, radius = args.near
        region = Region(x=x, y=y, radius=radius)
    request = Relocalize(stamp_ns=time.time_ns(), map_id=args.map, region=region)
    settings, session = client(args)
    with session:
        require_service(session, settings.prefix, settings.connect)
        if region is not None:  # a circle off the map: searched for ever, never found
            from service.keys import Keys

            fix = "leave out --near to search the whole map"
            for reply in session.get(Keys(settings.prefix).map(args.map), timeout=5.0):
                payload = None if reply.ok is None else reply.ok.payload.to_bytes()
                why = None if payload is None else off_map(payload, x, y, radius, fix=fix)
                if why is not None:
                    print(f"rlutf relocalize: refused: --near: {why}", file=sys.stderr)
                    return EXIT_FAILURE
        outcome = put_request(
            session, settings.prefix, args.robot, request, args.wait, show_event(args.json)
        )
    if args.wait <= 0:
        print(f"asked the service to relocalize {args.robot} on map {args.map}")
        return EXIT_OK
    if outcome.result == "done":
        if outcome.pose is not None and not args.json:
            print(pose_line(outcome.pose))
        return EXIT_OK
    if outcome.result == "refused":
        print(refused_hint("relocalize", args.map, outcome.code), file=sys.stderr)
    else:
        last = outcome.pose
        state: str = "no pose received" if last is None else last.status
        if last is not None and last.hypotheses:
            state += f", {len(last.hypotheses)} hypotheses"
        print(
            f"rlutf relocalize: {args.robot} not relocalized within {args.wait:g} s (last "
            f"status: {state}); is it sending scans? watch with `rlutf events {args.robot}`",
            file=sys.stderr,
        )
    return EXIT_FAILURE


def cmd_health(args: argparse.Namespace) -> int:
    """``rlutf health``: 0 if an instance answers."""
    from service.cli.present import health_problems, health_table
    from service.live.queries import fetch_health, live_instances

    if args.instance != "*":
        check_ids("health", instance=args.instance)
    settings, session = client(args)
    with session:
        healths = fetch_health(session, settings.prefix, args.instance, args.timeout)
        live = live_instances(session, settings.prefix) if not healths else []
    if not healths and args.instance != "*" and live:
        # the service runs, under other names: "is `rlutf serve` running?" sent one looking
        print(
            f"rlutf health: no instance {args.instance!r} on prefix {settings.prefix!r}; the "
            f"live instances are {', '.join(repr(i) for i in live)} (--instance NAME, or leave "
            "it out for all)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    if not healths:
        print(
            f"rlutf health: no instance answered on prefix {settings.prefix!r} within "
            f"{args.timeout:g} s; {unanswered_hint(args)}",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    if args.json:
        for h in healths:
            print(encode(h).decode())
    else:
        print(health_table(healths))
        for line in health_problems(healths):
            print(f"warning: {line}")
    return EXIT_OK


def refused_hint(command: str, map_id: str, code: str | None) -> str:
    """What to do when the service refused a request with an Event ``code`` (printed above)."""
    said = f"rlutf {command}: the service refused the request (see the Event above)"
    if code == EventCode.MAP_NOT_FOUND:
        return f"{said}; `rlutf map list` shows the stored maps (is {map_id!r} one?)"
    return f"{said}: the field it names is out of what the service accepts"
