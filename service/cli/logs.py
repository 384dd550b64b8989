"""The ``rlutf replay`` and ``rlutf log`` commands.

Exit codes:

* ``0``: done (replay: every recorded pose reproduced within the tolerance, or nothing to
  audit; recover: something was salvaged);
* ``1``: the audit failed (a recorded pose was not reproduced within the tolerance);
* ``2``: an input is missing, not MCAP, truncated or damaged (the message says to run
  ``rlutf log recover``), or the arguments or configuration are invalid.

Errors are one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli.flags import EXIT_OK

if TYPE_CHECKING:
    from rich.console import Console

EXIT_AUDIT_FAILED = 1
EXIT_BAD_INPUT = 2


def register(sub: Any) -> None:
    """Add ``replay`` and ``log`` to the ``rlutf`` subcommands."""
    replay = sub.add_parser(
        "replay",
        help="recompute the poses of a log and audit them",
        description="Run the service's localization over the inputs of one or more MCAP logs "
        "(maps, initial poses, odometry, scans; merged in log_time order) with the recorded "
        "configuration, write OUT with the inputs and the recomputed poses and events, and "
        "compare them with the poses the log holds. Scans the live service dropped under load "
        "(scan_dropped events) are dropped again. Exit 1 when a recorded pose deviates "
        "beyond the tolerance, 2 when an input cannot be read.",
    )
    replay.add_argument(
        "inputs",
        nargs="+",
        type=Path,
        metavar="IN",
        help="MCAP log(s), e.g. the rotated files of one run",
    )
    replay.add_argument(
        "--out", type=Path, required=True, metavar="OUT.mcap", help="the output log"
    )
    replay.add_argument(
        "--tolerance",
        type=float,
        default=1e-9,
        metavar="M",
        help="largest accepted deviation, metres (and radians unless "
        "--heading-tolerance is given); default 1e-9: exact",
    )
    replay.add_argument(
        "--heading-tolerance",
        type=float,
        metavar="RAD",
        help="largest accepted heading deviation, radians",
    )
    replay.add_argument(
        "--strict",
        action="store_true",
        help="also fail on recomputed poses after the log's last recorded one",
    )
    replay.add_argument(
        "--plot", type=Path, metavar="DIR", help="write a trajectory PNG per robot into DIR"
    )
    replay.add_argument(
        "--settings",
        type=Path,
        metavar="FILE",
        help="settings (JSON, TOML or YAML) merged over the recorded config",
    )
    replay.add_argument(
        "--set",
        dest="assignments",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one setting, e.g. localizer.epsilon=0.004 (repeatable)",
    )
    replay.add_argument(
        "--no-foxglove", action="store_true", help="leave the Foxglove views out of OUT"
    )
    replay.add_argument("--quiet", action="store_true", help="no progress bar")
    from service.cli.ros2bags import replay_flags

    replay_flags(replay)
    replay.set_defaults(func=cmd_replay)

    logs = sub.add_parser("log", help="inspect and repair MCAP logs")
    lsub = logs.add_subparsers(dest="log_command", metavar="ACTION")
    logs.set_defaults(func=lambda args: _usage(logs))
    info = lsub.add_parser(
        "info",
        help="channels, counts, time range, robots, maps",
        description="Describe a log. Exit 2 if it cannot be read.",
    )
    info.add_argument("file", type=Path)
    info.add_argument("--json", action="store_true", help="print JSON instead of tables")
    info.set_defaults(func=cmd_info)
    rec = lsub.add_parser(
        "recover",
        help="repair a log cut short by a crash",
        description="Copy every complete chunk (schemas, channels, messages) and every metadata "
        "record of a truncated or damaged MCAP file, such as a .mcap.part left by a crash, "
        "into a new valid file. Exit 2 if the input is not MCAP.",
    )
    rec.add_argument("broken", type=Path, metavar="BROKEN.mcap")
    rec.add_argument("out", type=Path, metavar="OUT.mcap")
    rec.set_defaults(func=cmd_recover)


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return EXIT_BAD_INPUT


def _console(stderr: bool = False) -> Console:
    """A console; tables keep their columns when the output is not a terminal."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, width=None if stream.isatty() else 132)


def _fail(command: str, err: Exception) -> int:
    print(f"rlutf {command}: {err}", file=sys.stderr)
    return EXIT_BAD_INPUT


def cmd_replay(args: argparse.Namespace) -> int:
    """``rlutf replay``."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from service.logs.audit import all_passed, audit, render
    from service.logs.mcapread import LogError
    from service.logs.replay import replay
    from service.logs.replayconfig import ReplayConfigError

    out: Path = args.out
    if any(out.resolve() == p.resolve() for p in args.inputs):
        return _fail("replay", ValueError(f"{out}: the output must not be an input"))
    err_console = _console(stderr=True)
    progress = Progress(
        "replaying",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err_console,
        disable=args.quiet,
        transient=False,
    )
    task = progress.add_task("replay", total=None)
    inputs, summary = list(args.inputs), None
    if args.ros2:
        from service.cli.ros2bags import bag_to_log

        if len(inputs) != 1:
            return _fail("replay", ValueError("--ros2 replays one bag"))
        inputs = [out.with_name(out.name + ".inputs.mcap")]
        try:
            summary = bag_to_log(args, args.inputs[0], inputs[0])
        except (ValueError, OSError) as err:
            inputs[0].unlink(missing_ok=True)
            return _fail("replay", err)
    try:
        with progress:
            result = replay(
                inputs,
                out,
                settings_file=args.settings,
                assignments=args.assignments,
                foxglove=not args.no_foxglove,
                progress=lambda n: progress.advance(task, n),
                on_total=lambda total: progress.update(task, total=total),
            )
    except (LogError, ReplayConfigError) as err:
        return _fail("replay", err)
    except OSError as err:
        return _fail("replay", ValueError(f"{err.filename or out}: {err.strerror or err}"))
    finally:
        if summary is not None:
            inputs[0].unlink(missing_ok=True)
    console = _console()
    if summary is not None:
        console.print(_bag_report(summary))
    recomputed = sum(len(v) for v in result.recomputed.values())
    console.print(
        f"replayed {result.inputs} inputs ({result.dropped} scans dropped as live, "
        f"{result.rejected} rejected): {recomputed} poses -> {out}"
    )
    if summary is not None and args.ros2_out is not None:
        from service.cli.ros2bags import write_out

        try:
            n = write_out(args, result, summary)
        except Exception as err:  # rosbags' writer raises its own errors
            return _fail("replay", ValueError(f"{args.ros2_out}: {err}"))
        console.print(f"wrote {n} ROS 2 messages (amcl_pose, tf) -> {args.ros2_out}")
    if args.plot is not None:
        from service.logs.plots import plot_all

        for path in plot_all(result, args.plot):
            console.print(f"wrote {path}")
    tol_m = args.tolerance
    tol_rad = args.heading_tolerance if args.heading_tolerance is not None else tol_m
    audits = audit(result.recorded, result.recomputed)
    if not audits:
        console.print("no recorded poses in the input: nothing to audit")
        return EXIT_OK
    render(audits, tol_m, tol_rad, console, args.strict)
    ok = all_passed(audits, tol_m, tol_rad, args.strict) and result.unreadable_poses == 0
    if result.unreadable_poses:
        console.print(
            f"[red]{result.unreadable_poses} recorded poses are not valid PoseEstimates[/red]"
        )
    console.print("audit: [green]passed[/green]" if ok else "audit: [bold red]FAILED[/bold red]")
    return EXIT_OK if ok else EXIT_AUDIT_FAILED


def _bag_report(summary: Any) -> str:
    counts = ", ".join(f"{n} {k}" for k, n in sorted(summary.counts.items()))
    text = f"bag: robot {summary.robot} ({summary.namespace}): {counts}"
    for why, n in summary.rejected.most_common(5):
        text += f"\n  rejected {n}: {why}"
    return text


def cmd_info(args: argparse.Namespace) -> int:
    """``rlutf log info``."""
    from service.logs.logtools import log_info, render_info
    from service.logs.mcapread import LogError

    try:
        info = log_info(args.file)
    except LogError as err:
        return _fail("log info", err)
    if args.json:
        print(json.dumps(info.to_json(), indent=2))
    else:
        render_info(info, _console())
    return EXIT_OK


def cmd_recover(args: argparse.Namespace) -> int:
    """``rlutf log recover``."""
    from service.logs.logtools import recover
    from service.logs.mcapread import LogError

    try:
        report = recover(args.broken, args.out)
    except LogError as err:
        return _fail("log recover", err)
    except OSError as err:
        return _fail("log recover", ValueError(f"{err.filename}: {err.strerror or err}"))
    state = (
        "complete (nothing was missing)"
        if report.complete and not report.resyncs
        else "read to its end"
        if report.complete
        else f"cut at byte {report.stopped_at} ({report.stopped})"
    )
    print(
        f"recovered {report.messages} messages in {report.chunks} chunks, "
        f"{report.metadata} metadata records -> {args.out}; input {state}"
    )
    if report.bad_chunks or report.lost_messages:
        print(
            f"skipped {report.bad_chunks} damaged chunks and {report.lost_messages} messages "
            "whose channel was lost",
            file=sys.stderr,
        )
    if report.resyncs:
        print(
            f"skipped {report.resyncs} unreadable stretch(es), the first at byte "
            f"{report.first_unreadable} ({report.first_problem}); reading resumed at the next "
            "chunk that checks out",
            file=sys.stderr,
        )
    if report.duplicate_chunks:
        print(f"dropped {report.duplicate_chunks} duplicated chunks", file=sys.stderr)
    return EXIT_OK
