"""Input files opened without a hang: only a regular file is read; and files replaced durably.

A FIFO named where a log, a map or a settings file is expected blocked ``open`` until something
wrote to it (``rlutf log info``, ``replay``, ``map import``, ``map show`` and ``map build`` hung
for ever), and a device such as ``/dev/zero`` was read until memory ran out. :func:`open_regular`
opens the path without blocking, checks what it is and refuses anything but a regular file with
an ``OSError`` whose ``strerror`` says what it is; callers report it as they report a missing
file.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from pathlib import Path
from typing import IO


def _not_a_file(mode: int) -> str | None:
    """What a path of this mode is, if it is not a regular file."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return os.strerror(errno.EISDIR)
    kind = (
        "a FIFO (named pipe)"
        if stat.S_ISFIFO(mode)
        else "a device"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "not a file"
    )
    return f"{kind}, not a regular file: copy what it holds into a file and give that"


def open_regular(path: Path | str) -> IO[bytes]:
    """Open a regular file for reading in binary mode.

    Raises:
        OSError: missing or unreadable, or not a regular file (a folder, a FIFO, a device, a
            socket): ``strerror`` says which.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        problem = _not_a_file(os.fstat(fd).st_mode)
        if problem is not None:
            code = errno.EISDIR if problem == os.strerror(errno.EISDIR) else errno.EINVAL
            raise OSError(code, problem, str(path))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def not_a_file(path: Path | str) -> str | None:
    """What ``path`` is if it exists and is not a regular file or a folder (a FIFO, a device, a
    socket), said as :func:`open_regular` says it; ``None`` otherwise. It does not open it."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    return None if stat.S_ISDIR(mode) else _not_a_file(mode)


def read_regular(path: Path | str, max_bytes: int | None = None) -> bytes:
    """The whole content of a regular file (see :func:`open_regular`).

    Args:
        max_bytes: the most that is read: a larger file is refused before more is read (what
            the caller takes has a size beyond which no real input goes, and memory is bounded
            whatever path a user gives).

    Raises:
        OSError: as :func:`open_regular`; ``EFBIG`` for a file over ``max_bytes``.
    """
    with open_regular(path) as stream:
        if max_bytes is None:
            return stream.read()
        size = os.fstat(stream.fileno()).st_size
        if size > max_bytes:
            raise too_large(path, max_bytes)
        # read(n) sets n bytes aside first: n is the file's size (+1 to see it grew), never the
        # bound (gigabytes held for a map file of a few kB).
        parts = [stream.read(size + 1)]
        got = len(parts[0])
        while got > size and got <= max_bytes and (more := stream.read(1 << 20)):
            parts.append(more)  # it grew while being read: on, a MiB at a time, to the bound
            got += len(more)
    if got > max_bytes:
        raise too_large(path, max_bytes)
    return b"".join(parts)


def too_large(path: Path | str, max_bytes: int) -> OSError:
    """The error of an input over ``max_bytes`` (its ``strerror`` names the size)."""
    return OSError(errno.EFBIG, f"larger than {max_bytes:,} bytes, the most read of it", str(path))


# ---------------------------------------------------------------------------- replaced files
# The embedded map store's maps and marks (service.maps.files) and the pose state
# (service.cluster.posestate) are replaced so: the new content is written to a temporary file
# beside the target, flushed to the disk, renamed over the target, and the folder itself flushed
# (the rename is only durable once the folder's entry is): a crash leaves the old content or the
# new, never half of either.


def replace_durably(path: Path, data: bytes, prefix: str) -> None:
    """Replace ``path`` with ``data`` atomically and durably.

    Args:
        path: the file; its folder must exist (it is not made: a folder gone, a volume
            unmounted, is an error, never a new folder on the disk beneath the mount point).
        data: the new content.
        prefix: the temporary file's name starts with it (a dot: hidden from listings).

    Raises:
        OSError: the folder is missing or refuses the write (full, read-only); the target is
            then as it was, and no temporary file is left.
    """
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    sync_folder(path.parent)


def sync_folder(folder: Path) -> None:
    """Flush a folder's entries to the disk (a rename or an unlink in it is durable after)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
