"""The ``rlutf`` command line: the service, its tools and the demo."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


def _zenoh_flags(p: argparse.ArgumentParser, *, client: bool) -> None:
    g = p.add_argument_group("zenoh (named like zenoh's own tools)")
    g.add_argument(
        "-m",
        "--mode",
        choices=["router", "peer", "client"],
        help="zenoh mode" + (" (default: client)" if client else " (default: router)"),
    )
    if not client:
        g.add_argument(
            "-l",
            "--listen",
            action="append",
            metavar="ENDPOINT",
            help="endpoint to listen on, repeatable (default: tcp/[::]:7447)",
        )
    g.add_argument(
        "-e",
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to connect to, repeatable"
        + (" (default: tcp/127.0.0.1:7447)" if client else ""),
    )
    g.add_argument("-c", "--config", type=Path, metavar="FILE", help="zenoh JSON5 config file")
    p.add_argument("--prefix", help="key prefix (default: rlutf)")


def _settings_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--settings",
        type=Path,
        metavar="FILE",
        help="settings file (JSON, TOML or YAML); also RLUTF_SETTINGS",
    )
    p.add_argument("--instance", help="instance name (default: host-pid)")
    p.add_argument("--store", type=Path, metavar="DIR", help="map store folder (default: store)")
    p.add_argument(
        "--no-store",
        action="store_true",
        default=None,
        help="do not host the map storage (use zenohd's storage manager)",
    )
    p.add_argument("--record", type=Path, metavar="DIR", help="MCAP log folder (default: logs)")
    p.add_argument("--no-record", action="store_true", default=None, help="do not record")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes (-1: one per core, the default; 0: in-process thread)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="rlutf",
        description="Fleet localization with RLuTF (Robot Localization using Turning Function) "
        "over Zenoh: robots publish scans and odometry, the service publishes corrected poses, "
        "records everything to MCAP and replays logs for audits.",
    )
    parser.add_argument(
        "--log-level",
        default="WARNING",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    serve = sub.add_parser(
        "serve",
        help="run the localization service",
        description="Run the service. Default: zenoh router on "
        "tcp/[::]:7447 with the embedded file-backed map store; robots "
        "connect straight to it. SIGINT/SIGTERM stop it gracefully.",
    )
    _zenoh_flags(serve, client=False)
    _settings_flags(serve)

    config = sub.add_parser(
        "config",
        help="print the effective configuration as JSON",
        description="Print the configuration the service would run with: "
        "defaults, settings file, RLUTF_* environment, then flags.",
    )
    _zenoh_flags(config, client=False)
    _settings_flags(config)

    demo = sub.add_parser(
        "demo",
        help="the service with a simulated fleet, live",
        description="Start the service on its embedded defaults, put a map "
        "into the store, and drive a simulated fleet (each robot its own "
        "Zenoh client session) at 10 Hz with drifting odometry. Shows a "
        "live table and a summary.",
    )
    demo.add_argument("--robots", type=int, default=5, help="simulated robots (default 5)")
    demo.add_argument("--duration", type=float, default=20.0, help="seconds (default 20)")
    demo.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    demo.add_argument("--beams", type=int, default=360, help="beams per scan (default 360)")
    demo.add_argument("--seed", type=int, default=0, help="world and fleet seed")
    demo.add_argument(
        "--port", type=int, default=0, help="router port on 127.0.0.1 (default: a free one)"
    )
    demo.add_argument("--store", type=Path, help="map store folder (default: a temporary one)")
    demo.add_argument(
        "--record", type=Path, default=Path("logs"), help="MCAP log folder (default: logs)"
    )
    demo.add_argument("--no-record", action="store_true", help="do not record")
    demo.add_argument("--workers", type=int, default=-1, help="service worker processes")
    demo.add_argument("--quiet", action="store_true", help="no live table, summary only")
    demo.add_argument("--verbose-health", action="store_true", help="print the final health")

    maps = sub.add_parser("map", help="put, get, import, build and show maps")
    msub = maps.add_subparsers(dest="map_command", metavar="ACTION")
    put = msub.add_parser("put", help="store a map (JSON Map message or GeoJSON geometry)")
    put.add_argument("file", type=Path)
    put.add_argument("--id", dest="map_id", help="map id (default: the file's map_id or stem)")
    put.add_argument("--version", type=int, help="version (default: the file's, else 1)")
    _zenoh_flags(put, client=True)
    get = msub.add_parser("get", help="print a stored map")
    get.add_argument("map_id")
    get.add_argument("--out", type=Path, help="write to a file instead of stdout")
    get.add_argument("--timeout", type=float, default=3.0)
    _zenoh_flags(get, client=True)
    from service.mapcli import register as register_map_commands

    register_map_commands(msub, _zenoh_flags)

    pose = sub.add_parser("pose", help="query the latest pose of one robot or all")
    pose.add_argument("robot", nargs="?", default="*", help="robot id (default: all)")
    pose.add_argument("--timeout", type=float, default=3.0)
    _zenoh_flags(pose, client=True)

    health = sub.add_parser("health", help="query instances' health; exit 1 if none answers")
    health.add_argument("--timeout", type=float, default=3.0)
    health.add_argument("--instance", default="*", help="instance name (default: all)")
    _zenoh_flags(health, client=True)

    from service.logcli import register as register_log_commands

    register_log_commands(sub)
    return parser


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def _load(args: argparse.Namespace) -> Any:
    from pydantic import ValidationError

    from service.config import load_settings

    try:
        return load_settings(
            args.settings,
            mode=args.mode,
            listen=args.listen,
            connect=args.connect,
            zenoh_config=args.config,
            prefix=args.prefix,
            instance=args.instance,
            store_dir=args.store,
            no_store=args.no_store,
            record_dir=args.record,
            no_record=args.no_record,
            workers=args.workers,
        )
    except ValidationError as err:
        raise SystemExit(f"rlutf: invalid configuration:\n{err}") from err
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"rlutf: {err}") from err


def cmd_config(args: argparse.Namespace) -> int:
    """Print the effective configuration."""
    print(json.dumps(_load(args).effective(), indent=2))
    return EXIT_OK


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the service until SIGINT or SIGTERM."""
    import zenoh

    from service.dispatch import tune_gc
    from service.node import LocalizationService
    from service.recording import make_recorder

    settings = _load(args)
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        logging.getLogger("rlutf").warning("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        service = LocalizationService(settings, recorder=make_recorder(settings)).start()
        tune_gc()
    except zenoh.ZError as err:
        print(f"rlutf serve: cannot open the zenoh session: {err}", file=sys.stderr)
        return EXIT_FAILURE
    print(
        f"rlutf serve: instance {settings.instance}, mode {settings.mode}, "
        f"listening on {', '.join(settings.listen) if settings.mode != 'client' else '-'}"
        f"{', connecting to ' + ', '.join(settings.connect) if settings.connect else ''}",
        file=sys.stderr,
        flush=True,
    )
    try:
        service.wait(stop)
    finally:
        service.close()
    return EXIT_OK


def _client(args: argparse.Namespace) -> Any:
    import zenoh

    from service.config import Settings

    settings = Settings(
        mode=args.mode or "client",
        connect=args.connect or ["tcp/127.0.0.1:7447"],
        listen=[],
        zenoh_config=args.config,
        **({"prefix": args.prefix} if args.prefix else {}),
    )
    from service.node import zenoh_config

    try:
        return settings, zenoh.open(zenoh_config(settings))
    except zenoh.ZError as err:
        raise SystemExit(
            f"rlutf: cannot reach zenoh at {', '.join(settings.connect)}: {err}"
        ) from err


def cmd_map(args: argparse.Namespace) -> int:
    """``rlutf map put|get``."""
    from service.tools import get_map, put_map

    if args.map_command == "put":
        settings, session = _client(args)
        with session:
            return put_map(session, settings.prefix, args.file, args.map_id, args.version)
    if args.map_command == "get":
        settings, session = _client(args)
        with session:
            return get_map(session, settings.prefix, args.map_id, args.out, args.timeout)
    print(
        "rlutf map: choose an action: put, get, import, build, show (see rlutf map --help)",
        file=sys.stderr,
    )
    return EXIT_USAGE


def cmd_pose(args: argparse.Namespace) -> int:
    """``rlutf pose [ROBOT]``."""
    from service.tools import query_poses

    settings, session = _client(args)
    with session:
        return query_poses(session, settings.prefix, args.robot, args.timeout)


def cmd_health(args: argparse.Namespace) -> int:
    """``rlutf health``: 0 if an instance answers."""
    from service.tools import query_health

    settings, session = _client(args)
    with session:
        return query_health(session, settings.prefix, args.instance, args.timeout)


def cmd_demo(args: argparse.Namespace) -> int:
    """``rlutf demo``."""
    from service.demo import run_demo

    return run_demo(args)


COMMANDS = {
    "serve": cmd_serve,
    "config": cmd_config,
    "demo": cmd_demo,
    "map": cmd_map,
    "pose": cmd_pose,
    "health": cmd_health,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``rlutf`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.log_level)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    func = getattr(args, "func", None) or COMMANDS[args.command]
    try:
        return int(func(args))
    except KeyboardInterrupt:
        return 130
