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
    if (gap := audit.gap_note(audits, result.gap_ns)) is not None:
        console.print(f"[yellow]{gap}[/yellow]", soft_wrap=True)
    if not audits and not result.unreadable_poses:
        console.print("no recorded poses in the input: nothing to audit")
        return audit.run_verdict(run, out, 0, poses, "nothing to audit")
    if not audits:  # every recorded pose is unreadable: none could be checked
        console.print(
            f"[red]{result.unreadable_poses} recorded poses are not valid PoseEstimates, and no "
            "other pose was recorded: none could be checked[/red]"
        )
        console.print("audit: [bold red]FAILED[/bold red]")
        return audit.run_verdict(run, out, 0, poses, "FAILED")
    audit.render(audits, tol_m, tol_rad, console, args.strict, heading)
    ok = audit.all_passed(audits, tol_m, tol_rad, args.strict) and result.unreadable_poses == 0
    if result.unreadable_poses:
        console.print(
            f"[red]{result.unreadable_poses} recorded poses are not valid PoseEstimates[/red]"
        )
    console.print("audit: [green]passed[/green]" if ok else "audit: [bold red]FAILED[/bold red]")
    note = None if ok else audit.version_note(run.files)
    if note is not None:
        console.print(f"[yellow]{note}[/yellow]")
    return audit.run_verdict(run, out, len(audits), poses, "passed" if ok else "FAILED")


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
