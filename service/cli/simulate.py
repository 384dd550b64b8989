"""``rlutf simulate``: simulated robots that join a running ``rlutf serve`` over Zenoh."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import signal
import sys
import threading
import time
from collections import Counter
from typing import Any

from service.cli.errors import zenoh_text
from service.cli.flags import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    ROS_DOMAIN_ID,
    SEED,
    checked_settings,
    with_file_endpoints,
    zenoh_file_config,
    zenoh_flags,
)
from service.cli.simreport import event_counter, progress, robot_of, summary

DESCRIPTION = """\
Simulated robots join a running `rlutf serve`: each drives its own path through a building
(there and back, over and over), puts drifting odometry and a noisy 2D scan at --rate, and
reads its corrected pose back, scored against the simulated truth. Try a site, a dashboard or
a deployment without robots.

The map: by default a building drawn from --seed is put into the service's store as --map;
with --stored-map the robots drive the map the store already holds under --map (a map
imported with `rlutf map import`, say). Each robot announces its true start as an
InitialPose, unless --no-initial-pose (the robots then wait, as a robot nobody placed does:
`rlutf relocalize ROBOT --map ID` finds one). --relocalize-every asks for a global
relocalization of the first robot now and then; --bad-input-every makes the first robot send
malformed or invalid scans now and then, which the service must refuse and count.

The robots are named r000, r001, ... (--names PREFIX: PREFIX000, ...). A robot id names one
robot to the service, so a second `rlutf simulate` beside a first (another map, say) needs
other names: the command listens a second for scans or poses of robots of its names before it
starts them, and refuses (exit 2) if something drives them already.

Prints what it does, then a line every --report-every seconds; stops after --duration seconds
or at Ctrl-C with a summary per robot. Exit code 1 when robots with an initial pose got no
pose back at all (is the service running, on this prefix?).
"""

#: Seconds the command listens for robots of its names driving already (scans, poses).
LISTEN_S = 1.0


def register(sub: Any) -> None:
    """Add ``simulate`` to the ``rlutf`` subcommands."""
    p = sub.add_parser(
        "simulate",
        help="simulated robots that join a running service",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=5, metavar="N", help="robots (default 5)")
    p.add_argument(
        "--rate", type=float, default=10.0, metavar="HZ", help="scans per second (default 10)"
    )
    p.add_argument(
        "--beams",
        type=int,
        default=360,
        metavar="N",
        help="beams a scan (default 360); the localizer compares a scan of at least "
        "min_returns returns (8 by default): fewer get no pose, only an Event lost",
    )
    p.add_argument(
        "--seed",
        type=SEED,
        default=0,
        help="seed of the building and the paths, 0 or more (default 0)",
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="SECONDS",
        help="stop after this long (default: run until Ctrl-C)",
    )
    p.add_argument(
        "--path-seconds",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="length of each robot's path before it turns back (default 30)",
    )
    p.add_argument(
        "--names",
        default="r",
        metavar="PREFIX",
        help="robot ids PREFIX000, PREFIX001, ... (default r: r000, r001, ...)",
    )
    p.add_argument("--map", default="sim", metavar="ID", help="map id (default: sim)")
    p.add_argument(
        "--stored-map",
        action="store_true",
        help="drive the map the store holds under --map instead of putting a new one",
    )
    p.add_argument("--no-initial-pose", action="store_true", help="robots announce no initial pose")
    p.add_argument(
        "--relocalize-every",
        type=float,
        metavar="SECONDS",
        help="a Relocalize for the first robot this often (JSON robots)",
    )
    p.add_argument(
        "--bad-input-every",
        type=float,
        metavar="SECONDS",
        help="a malformed or invalid scan from the first robot this often",
    )
    p.add_argument(
        "--report-every",
        type=float,
        default=5.0,
        metavar="SECONDS",
        help="seconds between progress lines (default 5)",
    )
    ros = p.add_argument_group("ROS 2 robots (the service runs with --ros2 --ros-map ID)")
    ros.add_argument(
        "--ros2", action="store_true", help="ROS 2 robots (CDR on rmw_zenoh's keys), not JSON"
    )
    ros.add_argument(
        "--ros-domain-id",
        type=ROS_DOMAIN_ID,
        default=0,
        metavar="N",
        help="ROS_DOMAIN_ID, 0 to 232, as the service's (default 0)",
    )
    ros.add_argument(
        "--humble", action="store_true", help="Humble's keys (no type hash), not Jazzy's"
    )
    zenoh_flags(p, client=True)
    p.set_defaults(func=cmd_simulate)


def _check(args: argparse.Namespace) -> str | None:
    """What is wrong with the flags, if anything."""
    from schemas import MAX_BEAMS, valid_id

    positive = {
        "--rate": args.rate,
        "--path-seconds": args.path_seconds,
        "--report-every": args.report_every,
        "--duration": args.duration,
        "--relocalize-every": args.relocalize_every,
        "--bad-input-every": args.bad_input_every,
    }
    for flag, value in positive.items():
        if value is not None and not (math.isfinite(value) and value > 0):
            return f"{flag} must be a number above 0, got {value}"
    if args.robots < 1:
        return f"--robots must be at least 1, got {args.robots}"
    if not 1 <= args.beams <= MAX_BEAMS:
        return f"--beams must be 1 to {MAX_BEAMS}, got {args.beams}"
    if not valid_id(args.map):
        return f"--map {args.map!r} is not a map id ([A-Za-z0-9_-], 1 to 64 characters)"
    last = f"{args.names}{max(args.robots, 1) - 1:03d}"  # as _ids, without the others
    if not valid_id(last):
        return f"--names {args.names!r} does not make robot ids ({last!r}: [A-Za-z0-9_-], 1 to 64)"
    if args.ros2 and args.relocalize_every:
        return "--relocalize-every: ROS 2 robots have no Relocalize topic; drop --ros2"
    from service.sim.fleet import memory_problem

    problem = memory_problem(_spec(args, named=False))  # before a too big fleet's ids
    return None if problem is None else f"{problem} (--robots, --path-seconds, --beams)"


def _ids(args: argparse.Namespace) -> tuple[str, ...]:
    return tuple(f"{args.names}{i:03d}" for i in range(max(args.robots, 1)))


class _Drivers:
    """Which of ``ids`` something drives on the bus now: scans put on their keys, or poses
    published for them, heard from when it is made until :meth:`taken` (at least
    :data:`LISTEN_S`). Other robots' samples cost a key test; a pose is read for its map once
    per robot of ``ids``."""

    def __init__(self, session: Any, keys: Any, ids: tuple[str, ...]) -> None:
        self._keys = keys
        self._ids = frozenset(ids)
        self._seen: dict[str, str | None] = {}
        self._lock = threading.Lock()
        self._since = time.monotonic()
        self._subs = [
            session.declare_subscriber(keys.robot("*", "scan"), self._on_scan),
            session.declare_subscriber(keys.all_poses, self._on_pose),
        ]

    def _robot(self, sample: Any) -> str | None:
        """The robot of a sample's key if it is one of ``ids``."""
        return robot_of(self._keys, self._ids, sample)

    def _on_scan(self, sample: Any) -> None:
        robot = self._robot(sample)
        if robot is not None:
            with self._lock:
                self._seen.setdefault(robot, None)

    def _on_pose(self, sample: Any) -> None:
        robot = self._robot(sample)
        if robot is None or self._seen.get(robot) is not None:
            return
        map_id = None
        with contextlib.suppress(ValueError, AttributeError):
            map_id = json.loads(sample.payload.to_bytes()).get("map_id")
        with self._lock:
            self._seen[robot] = map_id if isinstance(map_id, str) else self._seen.get(robot)

    def taken(self) -> str | None:
        """Which of the ids something drives, said as a refusal; ``None`` when none."""
        time.sleep(max(0.0, self._since + LISTEN_S - time.monotonic()))
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            busy = dict(self._seen)
        if not busy:
            return None
        names = ", ".join(f"{r} (map {busy[r]})" if busy[r] else r for r in sorted(busy)[:5]) + (
            f" and {len(busy) - 5} more" if len(busy) > 5 else ""
        )
        return (
            f"robots {names} already drive on this bus: two robots of one id would be one "
            "robot to the service, localized from both's inputs; name these robots apart "
            "with --names PREFIX (e.g. --names b), or stop the others first"
        )


def _spec(args: argparse.Namespace, named: bool = True) -> Any:
    """The fleet of the flags; ``named=False``: without the robots' ids, for sizing it."""
    from service.sim.plan import FleetSpec, Schedule

    rate = args.rate

    def every(seconds: float | None) -> Schedule | None:
        if seconds is None:
            return None
        steps = max(1, round(seconds * rate))
        return Schedule(every=steps, first=steps)

    return FleetSpec(
        robots=args.robots,
        poses=max(2, round(args.path_seconds * rate) + 1),
        rate_hz=rate,
        beams=args.beams,
        seed=args.seed,
        map_id=args.map,
        robot_ids=_ids(args) if named else (),
        initial_poses=not args.no_initial_pose,
        relocalize=every(args.relocalize_every),
        bad_input=every(args.bad_input_every),
    )


def _stored_world(session: Any, key: str, map_id: str) -> Any:
    """The map the store holds under ``key``, or ``None``."""
    from service.maps.book import MapRejected, load_map

    for reply in session.get(key, timeout=5.0):
        if reply.ok is not None:
            try:
                return load_map(reply.ok.payload.to_bytes(), expected_id=map_id, max_bytes=10**9)[1]
            except MapRejected:
                return None
    return None


def cmd_simulate(args: argparse.Namespace) -> int:
    """``rlutf simulate``."""
    import zenoh

    from service.config import Settings
    from service.keys import Keys
    from service.live.queries import fetch_health
    from service.live.sessions import zenoh_config
    from service.sim.fleet import SimFleet, drawing_bar, drive
    from service.sim.plan import plan_fleet
    from service.sim.score import Scoreboard
    from service.sim.wire import CdrWire, JsonWire

    problem = _check(args)
    if problem:
        print(f"rlutf simulate: {problem}", file=sys.stderr)
        return EXIT_USAGE
    settings = checked_settings(  # a bad RLUTF_* value: named, exit 2 (a ValidationError, 1)
        lambda: Settings(
            mode=args.mode or "client",
            listen=[],
            zenoh_config=args.config,
            **({"connect": args.connect} if args.connect else {}),
            **({"prefix": args.prefix} if args.prefix else {}),
        )
    )
    # The -c file's endpoints where -e gives none, as the other tools (the file was ignored: its
    # robots went to tcp/127.0.0.1:7447, and with a file that waits, timeout_ms -1, for ever).
    settings = with_file_endpoints(settings)
    keys = Keys(settings.prefix)
    where = ", ".join(settings.connect)
    config = zenoh_file_config(settings)  # an endpoint or -c/--config file zenoh refuses
    config.insert_json5("connect/timeout_ms", "0")  # asks once, as the other tools
    try:
        operator = zenoh.open(config)
    except zenoh.ZError as err:
        print(
            f"rlutf simulate: cannot reach zenoh at {where} ({zenoh_text(err)}); "
            "is `rlutf serve` "
            "running? name its endpoint with -e/--connect",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    with operator:
        drivers = _Drivers(operator, keys, _ids(args))
        world = None
        if args.stored_map:
            world = _stored_world(operator, keys.map(args.map), args.map)
            if world is None:
                print(
                    f"rlutf simulate: no valid map {args.map!r} in the store at {where}; put "
                    "one (`rlutf map put` or `rlutf map import`) or drop --stored-map",
                    file=sys.stderr,
                )
                return EXIT_FAILURE
        spec = _spec(args)
        door = "ROS 2" if args.ros2 else "JSON"
        print(
            f"rlutf simulate: drawing {spec.robots} {door} robots' paths "
            f"({args.path_seconds:g} s each, {spec.beams}-beam scans, seed {spec.seed})",
            flush=True,
        )
        drawing = time.monotonic()
        with drawing_bar(spec.robots) as advance:
            plan = plan_fleet(spec, world, on_robot=advance)
        if args.ros2:
            wire: Any = CdrWire(plan, args.ros_domain_id, "humble" if args.humble else "jazzy")
        else:
            wire = JsonWire(plan, keys)
        print(f"drawn and encoded in {time.monotonic() - drawing:.1f} s", flush=True)
        answered = fetch_health(operator, settings.prefix, "*", 1.0)
        if not answered:
            print(  # on with it: the service may be starting, and takes the robots then
                f"rlutf simulate: warning: no rlutf service answers on prefix "
                f"{settings.prefix!r} at {where} (`rlutf health` asks the same); the robots "
                "start anyway (is the service on another --prefix?)",
                file=sys.stderr,
                flush=True,
            )
        taken = drivers.taken()
        if taken is not None:
            print(f"rlutf simulate: {taken}", file=sys.stderr)
            return EXIT_USAGE
        fleet = SimFleet(plan, wire, lambda: zenoh.open(zenoh_config(settings)), keys=keys)
        stop = threading.Event()
        events: Counter[str] = Counter()
        bad = [0]
        try:
            told = "the stored one"
            if not args.stored_map and not answered:
                fleet.put_map()  # no service to wait for: put, unconfirmed
                told = "put, unconfirmed (no service answered)"
            elif not args.stored_map:
                put = fleet.store_map()
                if not put.stored:
                    print(f"rlutf simulate: {put.said}", file=sys.stderr)
                    return EXIT_FAILURE
                told = f"version {put.version} " + ("put" if put.new else "(held already)")
            walls = len(plan.world.segments)
            print(
                f"map {args.map}: {told}, "
                f"{walls} walls, {plan.world.geometry.area:.0f} m2; {spec.robots} robots at "
                f"{spec.rate_hz:g} Hz joining {where}; initial poses: "
                f"{'none (the robots wait for one)' if args.no_initial_pose else 'the true start'}"
                + (
                    f"; a Relocalize for {plan.robots[0].robot_id} every "
                    f"{args.relocalize_every:g} s"
                    if args.relocalize_every
                    else ""
                )
                + (
                    f"; bad input from {plan.robots[0].robot_id} every {args.bad_input_every:g} s"
                    if args.bad_input_every
                    else ""
                )
                + (f"; for {args.duration:g} s" if args.duration else "; Ctrl-C to stop"),
                flush=True,
            )
            t0 = time.time_ns()
            board = Scoreboard(plan, t0)

            plan_ids = tuple(robot.robot_id for robot in plan.robots)
            subs = [
                operator.declare_subscriber(
                    keys.all_poses, lambda s: board.on_pose(s.payload.to_bytes(), time.time_ns())
                ),
                operator.declare_subscriber(
                    keys.robot("*", "events"), event_counter(keys, plan_ids, events)
                ),
            ]
            fleet.start(t0)

            def on_step(step: int) -> None:
                bad[0] += sum(kind != "relocalize" for _, kind in plan.extras(step))
                fleet.extras(step, board.stamp(step))

            def send(robot: int, step: int) -> None:
                fleet.odometry(robot, step, board.stamp(step))
                board.sent(robot, step, time.time_ns())
                fleet.scan(robot, step, board.stamp(step))

            steps = None if args.duration is None else spec.steps_of(args.duration)
            robots = threading.Thread(
                target=drive,
                args=(spec.robots, 1.0 / spec.rate_hz, send, steps, stop, on_step),
                name="simulated-robots",
                daemon=True,
            )
            started = time.monotonic()
            robots.start()
            due = started + args.report_every
            # SIGTERM (`timeout`, `docker stop`, systemd) stops the fleet as Ctrl-C does, with
            # the summary; it ended the process on the spot, with no summary, before.
            main = threading.current_thread() is threading.main_thread()  # else: not ours
            previous = signal.signal(signal.SIGTERM, _interrupt) if main else None
            try:
                while robots.is_alive():
                    robots.join(max(0.0, min(0.5, due - time.monotonic())))
                    if time.monotonic() >= due:
                        print(progress(time.monotonic() - started, board, events, bad[0]))
                        due += args.report_every
            except KeyboardInterrupt:
                print("interrupted: stopping the robots", flush=True)
            finally:
                if main:
                    signal.signal(signal.SIGTERM, previous)
            stop.set()
            robots.join(5.0)
            time.sleep(0.5)  # the last poses
            for sub in subs:
                sub.undeclare()
            print(progress(time.monotonic() - started, board, events, bad[0]))
        finally:
            stop.set()
            fleet.close()
    print("\n".join(summary(board)))
    got = sum(s.poses for s in board.snapshot())
    if got == 0 and not args.no_initial_pose and events:
        # The service is up and answered, with Events only: they say why, not the network.
        heard = ", ".join(f"{code} {n}" for code, n in sorted(events.items()))
        print(
            f"rlutf simulate: no pose came back, though the service answered the robots with "
            f"Events ({heard}); `rlutf events ROBOT` says why (a scan of too few returns, "
            "with --beams under the localizer's min_returns, is lost and gets no pose)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    if got == 0 and not args.no_initial_pose:
        print(
            f"rlutf simulate: no pose came back; is `rlutf serve` running at {where} with "
            f"prefix {settings.prefix!r}"
            + (" and --ros2 --ros-map " + args.map if args.ros2 else "")
            + "?",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    return EXIT_OK


def _interrupt(_signum: int, _frame: object) -> None:
    """A SIGTERM taken as Ctrl-C: the robots stop and the summary is printed."""
    raise KeyboardInterrupt
