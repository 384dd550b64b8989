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
from collections.abc import Callable

from rlutf.warmup import kernels, warm_up

log = logging.getLogger(__name__)

#: The child's command: the same warm-up, in a process that exits after it.
_CHILD = "from rlutf.warmup import warm_up; warm_up()"
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


def warm_up_aside(progress: Callable[[str], None] | None = None) -> bool:
    """:func:`rlutf.warmup.warm_up` in this process, the kernels compiled by a child process
    first when numba's cache does not hold them.

    Returns:
        Whether this process compiled kernels anyway (the child failed, or the cache's index did
        not match the sources).
    """
    if not cache_holds_kernels():
        if progress is not None:
            progress(COMPILING)
        try:
            run = subprocess.run(
                [sys.executable, "-c", _CHILD],
                check=False,
                capture_output=True,
                text=True,
                timeout=CHILD_TIMEOUT_S,
            )
            if run.returncode != 0:
                log.warning("the kernels' warm-up process failed: %s", run.stderr[-2000:])
        except (OSError, subprocess.TimeoutExpired) as err:
            log.warning("the kernels' warm-up process failed: %s", err)
    compiled = warm_up()
    if compiled:
        log.info("this process compiled the localizer's kernels and keeps the compiler's memory")
    return compiled
