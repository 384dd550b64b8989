"""What a command says while the service starts: the wait for the localizer's kernels.

The first start after an install compiles the localizer's kernels (about 30 s on 2 cores);
later starts load them from numba's cache in about a second. The service tells its caller
what it waits for when the wait passes a few seconds; on a terminal the command shows that with
a spinner and the time waited, elsewhere (a container's log) as one line.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


@contextmanager
def starting_status(command: str) -> Iterator[Callable[[str], None]]:
    """A progress callback for :meth:`LocalizationService.start`, shown while the block runs.

    Args:
        command: the command's name, at the start of every line printed.
    """
    status: Any = None  # rich's Status, on a terminal only

    def progress(message: str) -> None:
        nonlocal status
        if sys.stderr.isatty():
            if status is None:
                # rich is imported here: a service in a container has no terminal, and its
                # modules would stay in memory for the service's life (2 MB).
                from rich.console import Console

                status = Console(stderr=True).status(f"{command}: {message}")
                status.start()
            else:
                status.update(f"{command}: {message}")
        else:
            print(f"{command}: {message}", file=sys.stderr, flush=True)

    try:
        yield progress
    finally:
        if status is not None:
            status.stop()
