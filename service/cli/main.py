"""The ``rlutf`` command line: one parser that registers each group's commands.

Every command, given input it cannot use, answers in a few lines naming the file or flag, the
problem and the fix, and exits non-zero (:mod:`service.cli.errors`); ``--debug`` shows the
traceback instead.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from importlib import metadata
from typing import Any, NoReturn

from service.cli import logs, maps, operate, query, robots, serve, simulate
from service.cli.errors import EXIT_FAILURE, EXIT_USAGE, explain
from service.kernelcache import writable_kernel_cache

#: The command groups, in the order ``rlutf --help`` lists their commands.
GROUPS = (serve, simulate, maps, query, operate, robots, logs)

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")

#: Flags whose value is a list of numbers that may start with a minus sign (``--pose
#: -1.5,2,0``): argparse would take such a value for a flag.
NUMBER_LISTS = ("--pose", "--near")
_NUMBERS = re.compile(r"^-[0-9.]")


class _Parser(argparse.ArgumentParser):
    """A parser whose every (sub)command accepts the global flags, before or after its name."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # SUPPRESS: a subcommand that is not given the flag leaves the top parser's value.
        self.add_argument(
            "--log-level",
            type=str.upper,
            choices=LOG_LEVELS,
            default=argparse.SUPPRESS,
            help="logging level (default WARNING)",
        )
        self.add_argument(
            "--debug",
            action="store_true",
            default=argparse.SUPPRESS,
            help="show the traceback of an unexpected error",
        )

    def error(self, message: str) -> NoReturn:
        """A bad flag in two lines (argparse would print the whole usage first)."""
        self.exit(EXIT_USAGE, f"{self.prog}: {message}\nsee `{self.prog} --help`\n")


def _version() -> str:
    try:
        return metadata.version("rlutf")
    except metadata.PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = _Parser(
        prog="rlutf",
        description="Fleet localization with RLuTF (Robot Localization using Turning Function) "
        "over Zenoh: robots publish scans and odometry, the service publishes corrected poses, "
        "records everything to MCAP and replays logs for audits.",
    )
    parser.add_argument(
        "--version",
        action="version",
        version=f"rlutf {_version()} (wire contract v1.2)",
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


def _join_number_lists(argv: list[str]) -> list[str]:
    """``--pose -1.5,2,0`` as ``--pose=-1.5,2,0``, so that argparse reads the value."""
    out: list[str] = []
    for i, arg in enumerate(argv):
        if out and out[-1] in NUMBER_LISTS and _NUMBERS.match(arg) and i > 0:
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


#: What an interrupted command did not do, said after ``interrupted`` (exit 130).
INTERRUPTED = {
    "replay": ": the audit did not finish, no verdict was given (exit 130); with --out, the "
    "output of the run being replayed was removed (a run's output named above is whole)",
}


def _name(args: argparse.Namespace) -> str:
    """The command as typed: ``rlutf log info``."""
    action = getattr(args, "map_command", None) or getattr(args, "log_command", None)
    return " ".join(w for w in ("rlutf", args.command, action) if w)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``rlutf`` console script."""
    parser = build_parser()
    args = parser.parse_args(_join_number_lists(sys.argv[1:] if argv is None else list(argv)))
    _setup_logging(getattr(args, "log_level", "WARNING"))
    # Before anything imports numba: a read-only cache (a read-only container) would stop the
    # kernels from loading at all.
    writable_kernel_cache()
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except KeyboardInterrupt:  # Ctrl-C: said, so that no one takes what was printed for all
        print(f"{_name(args)}: interrupted{INTERRUPTED.get(args.command, '')}", file=sys.stderr)
        return 130
    except Exception as err:
        if getattr(args, "debug", False):
            raise
        known = explain(err)
        name = _name(args)
        if known is None:
            print(
                f"{name}: unexpected error: {type(err).__name__}: {err}\n"
                "run it again with --debug for the traceback, and report it",
                file=sys.stderr,
            )
            return EXIT_FAILURE
        message, code = known
        print(f"{name}: {message}", file=sys.stderr)
        return code
