"""The ``rlutf replay`` and ``rlutf log`` commands.

Exit codes:

* ``0``: done (replay: every recorded pose reproduced within the tolerance, or nothing to
  audit; recover: something was salvaged);
* ``1``: the audit failed (a recorded pose of any run was not reproduced within the tolerance);
* ``2``: an input is missing, not MCAP, truncated or damaged (the message says to run
  ``rlutf log recover``), or the arguments or configuration are invalid; or (replay) the
  audit is incomplete: records of a run were not read (channels without a schema, what a
  salvage lost, files of the run not given: ``service.logs.completeness``). Given several
  files, replay names each unreadable file or run and audits the others first; an audit
  that failed then still exits 1.

Errors are one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli.flags import EXIT_OK, number, usable_folder, writable
from service.cli.present import console as make_console
from service.cli.present import unfinished

if TYPE_CHECKING:
    pass

EXIT_AUDIT_FAILED = 1
EXIT_BAD_INPUT = 2


def register(sub: Any) -> None:
    """Add ``replay`` and ``log`` to the ``rlutf`` subcommands."""
    replay = sub.add_parser(
        "replay",
        help="recompute the poses of a log and audit them",
        description="Sort the MCAP logs given into runs (metadata rlutf.run: the files one "
        "start of a service or replay wrote, in sequence order; files without it form one "
        "run), and for each run on its own: run the service's localization over its inputs "
        "(maps, initial poses, odometry, scans; merged in log_time order) with the recorded "
        "configuration, write (with --out) its output log with the inputs and the recomputed "
        "poses and events, and compare them with the poses the run recorded (matched as they "
        "come: the memory it takes does not grow with the run). Scans the live service "
        "dropped under load (scan_dropped events) are dropped again. Prints a table per run "
        "and, for several runs, one line per run. Exit 1 when a recorded pose of any run "
        "deviates beyond the tolerance or a file does not hold what its recorder listed in it "
        "(rlutf.manifest), 2 when an input cannot be read (a file with no rlutf message in "
        "it, such as a rosbag2 recording given without --ros2, is named with the command that "
        "reads it) or a run cannot be read whole (audit: incomplete: messages on channels "
        "without a schema, what rlutf log recover could not salvage, files of the run not "
        "given; each named).",
    )
    replay.add_argument(
        "inputs",
        nargs="+",
        type=Path,
        metavar="IN",
        help="MCAP logs, e.g. logs/*.mcap, or a folder of them (its *.mcap files, e.g. "
        "logs/): the files of one or several runs",
    )
    replay.add_argument(
        "--out",
        metavar="OUT",
        help="the output log (one run); with several runs OUT-run1.mcap, OUT-run2.mcap ...; "
        "a folder (existing, or written with a trailing /) gets one RUN.replay.mcap per run "
        "(default: none kept, an audit only)",
    )
    replay.add_argument(
        "--tolerance",
        type=number(float, minimum=0.0),
        default=1e-9,
        metavar="M",
        help="largest accepted deviation, metres (and radians unless "
        "--heading-tolerance is given); default 1e-9: exact",
    )
    replay.add_argument(
        "--heading-tolerance",
        type=number(float, minimum=0.0),
        metavar="RAD",
        help="largest accepted heading deviation, radians",
    )
    replay.add_argument(
        "--strict",
        action="store_true",
        help="also fail on recomputed poses after the log's last recorded one",
    )
    replay.add_argument(
        "--jobs",
        type=number(int, minimum=0),
        default=0,
        metavar="N",
        help="processes an audit alone (no --out, --plot or --ros2-out) is split between, by "
        "robot, each reading the whole run: the same verdict, in about 1/N of the time, at a "
        "lower priority (nice 10: a live service on the host keeps its cores); default 0: one "
        "per core this process may use, which is also the most; 1: one process",
    )
    plot = "write a trajectory PNG per robot into DIR (keeps every pose in memory: for a run "
    plot += "of hours, not weeks; without it the audit takes the same memory however long the run)"
    replay.add_argument("--plot", type=Path, metavar="DIR", help=plot)
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
        description="Describe logs. One file: its run, channels, time range, robots, maps, "
        "and what of it cannot be read (messages on channels without a schema, what a salvage "
        "lost) or differs from what its recorder listed in it (rlutf.manifest). "
        "Several files (e.g. logs/*.mcap): grouped by run (metadata rlutf.run; files without "
        "it form one run), per run its files in sequence order, time range, robots and maps; "
        'with --json an object {"runs": [...], "unreadable": [...]}. Exit 2 if a file cannot '
        "be read (among several: after describing the others).",
    )
    info.add_argument(
        "files", type=Path, nargs="+", metavar="FILE", help="MCAP logs, or folders of them"
    )
    info.add_argument("--json", action="store_true", help="print JSON instead of tables")
    info.set_defaults(func=cmd_info)
    rec = lsub.add_parser(
        "recover",
        help="repair a log cut short by a crash",
        description="Copy every complete chunk (schemas, channels, messages) and every metadata "
        "record (rlutf.run included) of a truncated or damaged MCAP file, such as a .mcap.part "
        "left by a crash, into a new valid file, with an rlutf.recovered metadata record that "
        "says what it could not copy (rlutf replay and rlutf log info read it). Several inputs, "
        "or an existing folder OUT: OUT "
        "is a folder (created if missing) that gets each one under its name without .part; the "
        "recovered files are listed by run. Exit 2 if an input is not MCAP, or declares a channel "
        "or schema id twice (differently), or nothing could be recovered from it (after "
        "recovering the others).",
    )
    rec.add_argument(
        "broken",
        type=Path,
        nargs="+",
        metavar="BROKEN.mcap",
        help="damaged logs, or folders (their unfinished *.mcap.part logs)",
    )
    rec.add_argument(
        "out",
        type=Path,
        metavar="OUT",
        help="the repaired log, or a folder to write into (needed for several: one log each, "
        "named as its input less .part)",
    )
    rec.set_defaults(func=cmd_recover)
    views = lsub.add_parser(
        "views",
        help="a copy of logs with their Foxglove views",
        description="Copy each log (every message, metadata record and schema) with the "
        "Foxglove views beside its messages: the map as a foxglove.SceneUpdate, each robot's "
        "foxglove.LaserScan and foxglove.PoseInFrame, and foxglove.FrameTransform on "
        "/foxglove/tf, so it opens in Foxglove with the map, the scans and the poses. The live "
        "service records them only with the setting record_views. The copy is of the same run "
        "(rlutf replay audits it as the original). One input: OUT is the file (or an existing "
        "folder, or a path ending in /); several: OUT is a folder that gets each under its "
        "name. Exit 2 if an input cannot be read.",
    )
    views.add_argument(
        "logs", type=Path, nargs="+", metavar="IN", help="MCAP logs, or folders of them"
    )
    views.add_argument("--out", required=True, metavar="OUT", help="file or folder")
    views.set_defaults(func=cmd_views)


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return EXIT_BAD_INPUT


def _fail(command: str, err: Exception) -> int:
    print(f"rlutf {command}: {err}", file=sys.stderr)
    return EXIT_BAD_INPUT


def cmd_replay(args: argparse.Namespace) -> int:
    """``rlutf replay``: sort the inputs into runs, replay and audit each on its own; with no
    ``--out`` an audit only (the recomputed logs are written aside, then removed)."""
    from service.cli.ros2bags import check_flags

    args.kept = args.out is not None
    check_flags(args)
    # Outputs that cannot be written are refused before a replay of hours, not after it.
    if args.plot is not None:
        usable_folder(args.plot, "--plot")
    if args.kept:
        out = Path(args.out)
        if out.is_dir() or str(args.out).endswith(("/", "\\")):
            usable_folder(out, "--out")
        else:
            writable(out, "--out")
        return _replay_runs(args)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="rlutf-replay-") as scratch:
        args.out = f"{scratch}/"
        return _replay_runs(args)


def _replay_runs(args: argparse.Namespace) -> int:
    from service.cli.runaudit import replay_one, report
    from service.logs.audit import (
        INCOMPLETE,
        UNREADABLE,
        render_verdicts,
        run_verdict,
        verdict_line,
    )
    from service.logs.mcapread import LogError
    from service.logs.replayconfig import ReplayConfigError
    from service.logs.runs import group_runs, log_files, run_outputs

    inputs, summary = list(args.inputs), None
    crashed = recording = 0
    if not args.ros2:  # a rosbag2 is a folder of its own
        try:
            inputs = log_files(inputs)
        except LogError as err:
            return _fail("replay", err)
        # A folder's unfinished logs are not read: one a crash left is a gap in the audit
        # (exit 2, as an unreadable file), one being recorded is audited once it is finished.
        crashed, recording = unfinished("replay", args.inputs, inputs, "not audited")
    if args.ros2:
        from service.cli.ros2bags import bag_to_log

        if len(inputs) != 1:
            return _fail("replay", ValueError("--ros2 replays one bag"))
        target = Path(args.out)
        inputs = [target.with_name(target.name + ".inputs.mcap")]
        try:
            summary = bag_to_log(args, args.inputs[0], inputs[0])
        except (ValueError, OSError) as err:
            inputs[0].unlink(missing_ok=True)
            return _fail("replay", err)
    unreadable: list[tuple[Path, LogError]] = []
    try:
        # One file that cannot be read stops a replay of one file; of several, it is named
        # and the other runs are audited (exit 2 at the end unless an audit failed).
        runs = group_runs(inputs, unreadable if len(inputs) > 1 else None, not args.ros2)
        for _path, bad in unreadable:
            _fail("replay", bad)
        if not runs:
            return EXIT_BAD_INPUT
        outs = run_outputs(args.out, runs)
        clash = next((o for o in outs for p in inputs if o.resolve() == p.resolve()), None)
        if clash is not None:
            raise ValueError(f"{clash}: the output must not be an input")
        if len(outs) > 1 or str(args.out).endswith(("/", "\\")):
            outs[0].parent.mkdir(parents=True, exist_ok=True)
        console = make_console()
        verdicts = []
        for k, (run, out) in enumerate(zip(runs, outs, strict=True), 1):
            if len(runs) > 1:
                console.rule(f"run {k} of {len(runs)}: {run.label}")
                console.print(f"files: {' '.join(str(f) for f in run.files)}")
            label = "replaying" if len(runs) == 1 else f"replaying run {k}/{len(runs)}"
            try:
                result = replay_one(args, run.files, out if args.kept else None, label)
            except LogError as err:  # a damaged chunk: this run cannot be audited
                if len(runs) == 1:
                    raise
                _fail("replay", err)
                verdicts.append(run_verdict(run, out, 0, 0, UNREADABLE))
                continue
            verdicts.append(report(args, console, result, summary, out, run, (k, len(runs))))
    except (LogError, ReplayConfigError, ValueError) as err:
        return _fail("replay", err)
    except OSError as err:
        return _fail("replay", ValueError(f"{err.filename or args.out}: {err.strerror or err}"))
    finally:
        if summary is not None:
            inputs[0].unlink(missing_ok=True)
    if len(verdicts) > 1:
        if not args.kept:
            verdicts = [dataclasses.replace(v, out="not kept") for v in verdicts]
        render_verdicts(verdicts, console)
    if len(verdicts) > 1 or unreadable or crashed or recording:
        console.print(verdict_line(verdicts, len(unreadable) + crashed, recording))
    if any(v.result == "FAILED" for v in verdicts):
        return EXIT_AUDIT_FAILED
    if unreadable or crashed or any(v.result in (UNREADABLE, INCOMPLETE) for v in verdicts):
        return EXIT_BAD_INPUT
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    """``rlutf log info``."""
    from service.logs.logtools import log_info, render_info, render_runs, runs_info
    from service.logs.mcapread import LogError
    from service.logs.runs import log_files

    unreadable: list[tuple[Path, LogError]] = []
    try:
        files = log_files(args.files)
        unfinished("log info", args.files, files, "not described")
        if len(files) == 1:
            info = log_info(files[0])
        else:  # one unreadable file among several is named, the others described
            runs = runs_info(files, unreadable)
    except LogError as err:
        return _fail("log info", err)
    if len(files) == 1:
        if args.json:
            print(json.dumps(info.to_json(), indent=2))
        else:
            render_info(info, make_console())
        return EXIT_OK
    for _path, bad in unreadable:
        _fail("log info", bad)
    if args.json:
        named = [{"path": str(p), "error": str(e)} for p, e in unreadable]
        print(json.dumps({"runs": [r.to_json() for r in runs], "unreadable": named}, indent=2))
    else:
        render_runs(runs, make_console())
    return EXIT_BAD_INPUT if unreadable else EXIT_OK


def cmd_recover(args: argparse.Namespace) -> int:
    """``rlutf log recover``."""
    from service.logs.mcapread import LogError
    from service.logs.runs import group_runs, log_files
    from service.logs.salvage import recover

    try:
        broken_logs = log_files(args.broken, ".mcap.part")
    except LogError as err:
        return _fail("log recover", err)
    outs = [args.out]
    several = len(broken_logs) > 1 or any(p.is_dir() for p in args.broken)
    if several or args.out.is_dir():
        usable_folder(args.out, "OUT")
        outs = [args.out / p.name.removesuffix(".part") for p in broken_logs]
    else:
        writable(args.out, "OUT")
    empty: list[Path] = []  # outputs not written: nothing to salvage, or the input refused
    for broken, out in zip(broken_logs, outs, strict=True):
        try:
            report = recover(broken, out)
        except LogError as err:  # this input is named; the others are recovered all the same
            _fail("log recover", err)
            empty.append(out)
            continue
        except OSError as err:
            return _fail("log recover", ValueError(f"{err.filename}: {err.strerror or err}"))
        damaged = report.bad_chunks or report.lost_messages or report.resyncs
        if not report.complete:
            state = f"the input is cut at byte {report.stopped_at} ({report.stopped})"
        elif damaged:
            state = "the input was read to its end"
        else:
            state = "the input was read to its end, nothing was missing"
        if report.messages == 0:  # nothing salvaged: no empty log left to be taken for one
            out.unlink(missing_ok=True)
            empty.append(out)
            print(
                f"rlutf log recover: {broken}: no message could be recovered ({state}); "
                "no output written",
                file=sys.stderr,
            )
            continue
        print(
            f"recovered {report.messages} messages in {report.chunks} chunks, "
            f"{report.metadata} metadata records -> {out}; {state}"
        )
        if report.bad_chunks or report.lost_messages:
            print(
                f"{broken}: skipped {report.bad_chunks} damaged chunk(s) and "
                f"{report.lost_messages} message(s) whose channel was lost: those messages "
                "are not in the output",
                file=sys.stderr,
            )
        if report.resyncs:
            print(
                f"{broken}: skipped {report.resyncs} unreadable stretch(es), the first at byte "
                f"{report.first_unreadable} ({report.first_problem}); reading resumed at the "
                "next chunk that checks out",
                file=sys.stderr,
            )
        if report.duplicate_chunks:
            print(
                f"{broken}: dropped {report.duplicate_chunks} duplicated chunk(s)", file=sys.stderr
            )
    outs = [out for out in outs if out not in empty]
    if len(outs) > 1:
        try:
            runs = group_runs(outs)
        except LogError as err:
            return _fail("log recover", err)
        for k, run in enumerate(runs, 1):
            tags = ", ".join("-" if t is None else str(t.sequence) for t in run.tags)
            print(f"run {k}: {run.label}: file(s) {tags}: {' '.join(map(str, run.files))}")
    return EXIT_BAD_INPUT if empty else EXIT_OK


def cmd_views(args: argparse.Namespace) -> int:
    """``rlutf log views``."""
    from service.logs.mcapread import LogError
    from service.logs.runs import log_files
    from service.logs.views import write_views

    out = Path(args.out)
    try:
        logs = log_files(args.logs)
    except LogError as err:
        return _fail("log views", err)
    unfinished("log views", args.logs, logs, "not copied")
    folder = any(p.is_dir() for p in args.logs) or str(args.out).endswith(("/", "\\"))
    outs = [out / p.name for p in logs] if len(logs) > 1 or out.is_dir() or folder else [out]
    clash = next((o for o in outs for p in logs if o.resolve() == p.resolve()), None)
    if clash is not None:
        return _fail("log views", ValueError(f"{clash}: the output must not be an input"))
    try:
        outs[0].parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return _fail("log views", ValueError(f"{err.filename}: {err.strerror or err}"))
    for src, dst in zip(logs, outs, strict=True):
        try:
            report = write_views(src, dst)
        except LogError as err:
            return _fail("log views", err)
        except OSError as err:
            return _fail("log views", ValueError(f"{err.filename}: {err.strerror or err}"))
        again = f" ({report.replaced} views of the input written anew)" if report.replaced else ""
        print(
            f"{src}: {report.messages} messages, {report.views} Foxglove views, "
            f"{report.metadata} metadata records -> {dst}{again}"
        )
    return EXIT_OK
