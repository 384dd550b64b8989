"""Warm up a process that localizes itself without keeping the compiler's memory.

A process that compiles the localizer's kernels keeps numba's and LLVM's memory for as long as
it runs: about 290 MB resident after the warm-up against about 160 MB for one that loaded them
from numba's cache (:func:`rlutf.warmup.compiled_here`). Worker processes that compiled are
replaced (:mod:`service.live.dispatch`); a process that runs its robots itself (``--workers 0``,
and each process of ``--processes N``) cannot be, so on a first start after an install a child
process compiles the kernels into the cache first, and this process then loads them.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable

from rlutf.warmup import kernels, warm_up

log = logging.getLogger(__name__)

#: The child's command: the same warm-up, in a process that exits after it, or as soon as the
#: process that started it is gone (``kill -9`` of a starting service left it compiling).
_CHILD = (
    "import os, threading, time\n"
    "parent = os.getppid()\n"
    "def orphaned():\n"
    "    while os.getppid() == parent:\n"
    "        time.sleep(0.5)\n"
    "    os._exit(1)\n"
    "threading.Thread(target=orphaned, daemon=True).start()\n"
    "from rlutf.warmup import warm_up; warm_up()\n"
)
#: What a start says while the kernels compile.
COMPILING = (
    "compiling the localizer's kernels (first start only; about 30 s on 2 cores, then they load "
    "from numba's cache in about a second)"
)
#: Seconds the child may take (a cold compile takes about 25 s on 2 idle cores).
CHILD_TIMEOUT_S = 600.0


def cache_holds_kernels() -> bool:
    """Whether numba's cache has an index for every kernel of the localizer (a first start after
    an install has none).

    A quick look, not a proof: an index written for other sources is found too (the warm-up
    then compiles here, as without this check). ``False`` when numba's cache is not laid out as
    this code knows (numba 0.6x's ``FunctionCache``), so a child warms up first, to be safe.
    """
    try:
        return all(os.path.exists(k._cache._cache_file._index_path) for k in kernels())
    except AttributeError:
        return False


def warm_up_aside(
    progress: Callable[[str], None] | None = None, stop: threading.Event | None = None
) -> bool:
    """:func:`rlutf.warmup.warm_up` in this process, the kernels compiled by a child process
    first when numba's cache does not hold them.

    Args:
        progress: told once, when a child compiles (the wait is explained).
        stop: set when the service is told to stop (SIGTERM, Ctrl-C): the child is ended and
            nothing is warmed up. (Before, a service stopped while its child compiled went on
            until the compile ended, 30 s on 2 idle cores and minutes on busy ones, then
            compiled nothing it needed: a supervisor's grace period ran out first.)

    Returns:
        Whether this process compiled kernels anyway (the child failed, or the cache's index did
        not match the sources); ``False`` when stopped first.
    """
    if not cache_holds_kernels():
        if progress is not None:
            progress(COMPILING)
        if not _compile_in_child(stop):
            return False
    compiled = warm_up()
    if compiled:
        log.info("this process compiled the localizer's kernels and keeps the compiler's memory")
    return compiled


def _compile_in_child(stop: threading.Event | None) -> bool:
    """Run the warm-up child to its end; ``False`` if ``stop`` was set first (the child ended)."""
    try:
        child = subprocess.Popen(
            [sys.executable, "-c", _CHILD],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
    except OSError as err:
        log.warning("the kernels' warm-up process failed: %s", err)
        return True
    # stderr is read on a thread, so a chatty child never blocks on a full pipe
    errors: list[str] = []
    reader = threading.Thread(
        target=lambda: errors.append(child.stderr.read() if child.stderr else ""),
        name="rlutf-warmup-stderr",
        daemon=True,
    )
    reader.start()
    deadline = time.monotonic() + CHILD_TIMEOUT_S
    waiting = stop if stop is not None else threading.Event()
    while child.poll() is None:
        if waiting.wait(0.2) or time.monotonic() > deadline:
            child.kill()
            child.wait()
            reader.join(5.0)
            if waiting.is_set():
                return False
            log.warning(
                "the kernels' warm-up process failed: timed out after %.0f s", CHILD_TIMEOUT_S
            )
            return True
    reader.join(5.0)
    if child.returncode != 0:
        log.warning("the kernels' warm-up process failed: %s", "".join(errors)[-2000:])
    return True
