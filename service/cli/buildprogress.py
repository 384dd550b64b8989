"""What ``rlutf map build`` shows while it reads a log: the scans read, pass by pass.

The grid is built in two readings of the log (its extent, then its cells: the scans are read
again rather than held), about 3 ms a scan on 2 cores, so a bag of an hour's mapping takes
minutes with nothing else to show for it. On a terminal each reading gets a bar (the first
counts the scans, the second knows how many there are); elsewhere (a pipe, a CI log) nothing
is printed.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from rich.console import Console

T = TypeVar("T")
#: What each reading of the log is for (``build_grid`` reads it twice).
PASSES = ("its extent", "its cells")


@contextmanager
def reading_scans(
    name: str, console: Console | None = None
) -> Iterator[Callable[[Iterable[T] | Callable[[], Iterable[T]]], Callable[[], Iterator[T]]]]:
    """A context giving ``counted``: ``counted(scans)`` reads ``scans`` (a sequence, or a function
    giving them anew) as ``build_grid`` does, each reading shown as a progress bar.

    Args:
        name: the log's name, in each bar's label.
        console: where the bars go (default: standard error, shown only on a terminal).
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from service.cli.present import console as make_console

    shown = console if console is not None else make_console(stderr=True)
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=shown,
        disable=console is None and not sys.stderr.isatty(),
    )

    def counted(scans: Iterable[T] | Callable[[], Iterable[T]]) -> Callable[[], Iterator[T]]:
        if not callable(scans) and not isinstance(scans, Sequence):
            scans = list(scans)  # read once only: held, as build_grid holds it
        state: dict[str, Any] = {"readings": 0, "scans": None}

        def read() -> Iterator[T]:
            state["readings"] += 1
            n = state["readings"]
            what = PASSES[n - 1] if n <= len(PASSES) else f"reading {n}"
            task = progress.add_task(f"map build: {name}, scans for {what}", total=state["scans"])
            done = 0
            for scan in scans() if callable(scans) else scans:
                done += 1
                progress.advance(task)
                yield scan
            state["scans"] = done
            progress.update(task, total=done, completed=done)

        return read

    with progress:
        yield counted
