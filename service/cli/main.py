"""The ``rlutf`` command line: one parser that registers each group's commands."""

from __future__ import annotations

import argparse
import logging
import sys

from service.cli import logs, maps, query, robots, serve, simulate
from service.cli.flags import EXIT_USAGE

#: The command groups, in the order ``rlutf --help`` lists their commands.
GROUPS = (serve, simulate, maps, query, robots, logs)


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
    for group in GROUPS:
        group.register(sub)
    return parser


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``rlutf`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.log_level)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return 130
