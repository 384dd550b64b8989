"""Unfinished logs: what a ``.mcap.part`` file is, and whether its recorder is still writing it.

The recorder writes a log as ``NAME.mcap.part`` and renames it ``NAME.mcap`` when it is finished;
one not written for :data:`RECENT_S` was left by a recorder that crashed or was killed.
"""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

#: A ``.mcap.part`` modified this recently is taken to be still recorded, seconds.
RECENT_S = 60.0


def _age(path: Path, now: float | None = None) -> float | None:
    try:
        return (time.time() if now is None else now) - path.stat().st_mtime
    except OSError:
        return None


def left_unfinished(path: Path, now: float | None = None) -> bool:
    """Whether a ``.mcap.part`` was left by a recorder that crashed or was killed (not written
    for :data:`RECENT_S`), rather than being recorded now."""
    age = _age(path, now)
    return age is not None and age >= RECENT_S


def part_message(path: Path, now: float | None = None) -> str:
    """What a ``.mcap.part`` file is and how to read it now.

    The recorder writes a log as ``NAME.mcap.part`` and renames it ``NAME.mcap`` when it is
    finished (rotation or a stop); until then it has no summary, and its last chunk may be
    half-written. Its complete chunks (flushed at least every second) can be copied out.
    """
    age = _age(path, now)
    state = (
        f"is being recorded now (last written {age:.0f} s ago)"
        if age is not None and age < RECENT_S
        else "was left unfinished (its recorder crashed or was killed)"
        if age is not None
        else "is unfinished"
    )
    final = path.name.removesuffix(".part")
    if age is not None and age >= RECENT_S:  # no service will finish it (it was told so before)
        return (
            f"{path}: this log {state}: a .mcap.part file has no index, and this one will not be "
            f"finished and renamed {final}. To read it, copy its complete chunks: rlutf log "
            f"recover {path} COPY.mcap (the .part file is not changed), then use COPY.mcap"
        )
    return (
        f"{path}: this log {state}: a .mcap.part file has no index until the service finishes "
        f"it (at rotation, record_max_seconds, or when it stops) and renames it {final}. "
        f"To read it now, copy its complete chunks: rlutf log recover {path} COPY.mcap "
        "(the file being recorded is not touched), then use COPY.mcap"
    )


def check_in_place(path: Path, fd: int) -> None:
    """Raise ``FileNotFoundError`` when the file open as ``fd`` is no longer at ``path``.

    A log removed while it was written (by hand, or with its folder) took every write without an
    error: the recorder wrote into a file nobody could find until its rotation, up to an hour
    later, said nothing, and lost it all. The recorder checks this at each flush.
    """
    held = os.fstat(fd)
    try:
        found = os.stat(path)
    except FileNotFoundError:
        found = None
    if found is None or (found.st_dev, found.st_ino) != (held.st_dev, held.st_ino):
        raise FileNotFoundError(
            errno.ENOENT,
            "the log being written was removed or moved (with its folder?), and what it held "
            "since it was opened with it; the folder is not made again",
            str(path),
        )
