"""A process that runs its robots itself does not compile the localizer's kernels: on a first
start after an install a child process compiles them into numba's cache, and it loads them.

(A process that compiled keeps the compiler's memory for as long as it runs, about 130 MB more.)
Real processes, a real (empty, then filled) numba cache.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

_START = """
from service.live.warmaside import cache_holds_kernels, warm_up_aside
said = []
before = cache_holds_kernels()
compiled = warm_up_aside(said.append)
print(before, compiled, len(said), cache_holds_kernels())
"""


def _start(cache: Path) -> list[str]:
    run = subprocess.run(
        [sys.executable, "-c", _START],
        check=False,
        env={**os.environ, "NUMBA_CACHE_DIR": str(cache)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    return run.stdout.split()


def test_a_first_start_compiles_aside_and_a_second_start_loads(tmp_path: Path) -> None:
    cache = tmp_path / "numba"
    # First start after an install: nothing cached; a child compiles, this process loads, and
    # the wait is explained once.
    assert _start(cache) == ["False", "False", "1", "True"]
    # Next start: the cache holds every kernel; no child, nothing said, nothing compiled.
    assert _start(cache) == ["True", "False", "0", "True"]
