"""One run of ``rlutf replay``: its replay (split between processes when only audited) and
its report."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.cli.present import console as make_console

if TYPE_CHECKING:
    from rich.console import Console


def replay_one(
    args: argparse.Namespace, files: Sequence[Path], out: Path | None, label: str
) -> Any:
    """One run replayed (into ``out`` unless ``None``); its poses are kept only for ``--plot``
    and ``--ros2-out``: the audit counts as it goes (``service.logs.posematch``). An audit alone
    (no ``--out``, ``--plot`` or ``--ros2-out``) is split between ``--jobs`` processes by robot
    (``service.logs.split``)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from service.logs.replay import replay, run_config
    from service.logs.split import replay_split

    keep = args.plot is not None or args.ros2_out is not None
    progress = Progress(
        label,
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=make_console(stderr=True),
        disable=args.quiet,
        transient=False,
    )
    task = progress.add_task("replay", total=None)
    with progress:
        split = jobs(args) if out is None and not keep else 1
        if split > 1:
            return replay_split(
                files,
                run_config(files, args.settings, args.assignments),
                split,
                progress=lambda n: progress.advance(task, n),
                on_total=lambda total: progress.update(task, total=total),
            )
        return replay(
            files,
            out,
            settings_file=args.settings,
            assignments=args.assignments,
            foxglove=not args.no_foxglove,
            progress=lambda n: progress.advance(task, n),
            on_total=lambda total: progress.update(task, total=total),
            keep=keep,
        )


def jobs(args: argparse.Namespace) -> int:
    """The processes ``--jobs`` asks for (0: one per core this process may use, also the most:
    more would only share the cores, each with the memory of an audit)."""
    from service.cores import usable_cores

    cores = usable_cores()
    return min(int(args.jobs), cores) if args.jobs > 0 else cores


def report(
    args: argparse.Namespace,
    console: Console,
    result: Any,
    summary: Any,
    out: Path,
    run: Any,
    place: tuple[int, int],
) -> Any:
    """Print one run's replay and audit (run ``k`` of ``n`` = ``place``); its line for the
    final summary."""
    from rich.markup import escape

    from service.logs import audit

    k, n = place
    heading = "Audit" if n == 1 else f"Audit of run {k}"
    if summary is not None:
        console.print(bag_report(summary))
    recomputed = result.match.recomputed_total
    console.print(
        f"replayed {result.inputs} inputs ({result.dropped} scans dropped as live, "
        f"{result.rejected} rejected): {recomputed} poses -> "
        f"{out if args.kept else 'not kept (--out keeps them)'}",
        soft_wrap=True,  # one line whatever the width: a path or a grep is not cut in two
    )
    if summary is not None and args.ros2_out is not None:
        from service.cli.ros2bags import write_out

        try:
            poses, transforms = write_out(args, result, summary)
        except Exception as err:  # rosbags' writer raises its own errors
            raise ValueError(f"{args.ros2_out}: {err}") from err
        tf = f"{transforms} tf" if transforms else "no tf (no odometry at the poses' stamps)"
        console.print(f"wrote {poses} amcl_pose, {tf} -> {args.ros2_out}", soft_wrap=True)
    if args.plot is not None:
        from service.logs.plots import plot_all

        folder = args.plot if n == 1 else args.plot / f"run{k}"
        for path in plot_all(result, folder):
            console.print(f"wrote {path}", soft_wrap=True)
    tol_m = args.tolerance
    tol_rad = args.heading_tolerance if args.heading_tolerance is not None else tol_m
    audits = audit.audit_match(result.match)
    poses = result.match.recorded_total
    whole = result.completeness
    if (gap := audit.gap_note(audits, result.gap_ns)) is not None:
        console.print(f"[yellow]{gap}[/yellow]", soft_wrap=True)
    empty = not audits and not result.unreadable_poses
    for kind, text in whole.notes():
        if kind != "note" or not empty:  # a note qualifies an audit: none, none to qualify
            colour = {"altered": "red", "incomplete": "bold yellow"}.get(kind, "yellow")
            console.print(f"[{colour}]{escape(text)}[/{colour}]", soft_wrap=True)
    if empty and not whole.incomplete and not whole.altered:
        console.print("no recorded poses in the input: nothing to audit")
        return audit.run_verdict(run, out, 0, poses, "nothing to audit")
    affected = whole.affected() if whole.incomplete else frozenset()
    marked = {a.robot for a in audits} if affected is None else affected
    if audits:
        audit.render(audits, tol_m, tol_rad, console, args.strict, heading, marked)
    elif result.unreadable_poses:  # every recorded pose is unreadable: none could be checked
        console.print(
            f"[red]{result.unreadable_poses} recorded poses are not valid PoseEstimates, and no "
            "other pose was recorded: none could be checked[/red]"
        )
    failed = [
        a for a in audits if a.robot not in marked and not a.passed(tol_m, tol_rad, args.strict)
    ]
    if result.unreadable_poses and audits:
        console.print(
            f"[red]{result.unreadable_poses} recorded poses are not valid PoseEstimates[/red]"
        )
    if failed or whole.altered or result.unreadable_poses:
        verdict = "FAILED"
        console.print("audit: [bold red]FAILED[/bold red]")
        note = audit.version_note(run.files) if failed else None
        if note is not None:
            console.print(f"[yellow]{note}[/yellow]")
    elif whole.incomplete:
        verdict = audit.INCOMPLETE
        console.print(
            "audit: [bold yellow]incomplete[/bold yellow]: records of the log were not read "
            "(above), so the audit can neither pass it nor find it altered"
            + ("; the other robots passed" if len(marked) < len(audits) else ""),
            soft_wrap=True,
        )
    else:
        verdict = "passed"
        console.print("audit: [green]passed[/green]")
    return audit.run_verdict(run, out, len(audits), poses, verdict)


def bag_report(summary: Any) -> str:
    """What a bag's conversion read, left out and warns of (rich markup)."""
    from rich.markup import escape

    counts = ", ".join(f"{n} {k}" for k, n in sorted(summary.counts.items()))
    text = f"bag: robot {summary.robot} ({summary.namespace}): {counts}"
    for why, n in summary.rejected.most_common(5):
        text += f"\n  rejected {n}: {why}"
    for warning in summary.warnings:
        text += f"\n[yellow]  warning: {escape(warning)}[/yellow]"
    return text
