"""A writable folder for numba's cache of the localizer's compiled kernels.

numba loads a cached kernel only through a cache folder it can write to: each of its ways of
finding the folder (``NUMBA_CACHE_DIR``, ``__pycache__`` beside the package, the user's cache
folder) first writes a temporary file there, and when none can be written, importing the kernels
raises ``RuntimeError: cannot cache function ...: no locator available``. A container with a
read-only root file system (``deploy/k8s``: ``readOnlyRootFilesystem: true``; ``docker run
--read-only``) has the image's kernels, compiled at build time into ``NUMBA_CACHE_DIR``, on a
file system nothing can write to, so the service would not start at all.

:func:`writable_kernel_cache`, called before anything imports numba, leaves a writable
``NUMBA_CACHE_DIR`` as it is; an unwritable one is copied (a few MB) into the temporary folder
(``/tmp``, an ``emptyDir`` in the Kubernetes manifest) and ``NUMBA_CACHE_DIR`` points there, for
this process and the processes it starts. The copy keeps the files' contents and the index
that names the package's source files, so the kernels load from it as from the original, without
compiling.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

#: The environment variable numba reads its cache folder from.
VARIABLE = "NUMBA_CACHE_DIR"


def writable(folder: Path) -> bool:
    """Whether ``folder`` exists or can be made, and a file can be written in it (numba's own
    test of a cache folder)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def writable_kernel_cache(
    environ: dict[str, str] | os._Environ[str] = os.environ,
    temporary: Path | None = None,
    can_write: Callable[[Path], bool] = writable,
) -> Path | None:
    """Make ``environ``'s ``NUMBA_CACHE_DIR`` a folder numba can use (see the module docstring).

    Args:
        environ: the environment to read and change (this process's by default).
        temporary: where a copy goes (default: the system's temporary folder).
        can_write: the test of a folder.

    Returns:
        The folder ``NUMBA_CACHE_DIR`` now names if it was changed, else ``None`` (unset, or
        writable: numba's own choice stands).
    """
    given = environ.get(VARIABLE)
    if not given or can_write(Path(given)):
        return None
    base = Path(tempfile.gettempdir()) if temporary is None else temporary
    copy = base / f"rlutf-numba-cache-{os.getuid() if hasattr(os, 'getuid') else 0}"
    if not can_write(copy):
        log.warning(
            "numba's cache %s is read-only and %s cannot be written either: the localizer's "
            "kernels cannot load; mount a writable volume at %s (or set %s)",
            given,
            copy,
            given,
            VARIABLE,
        )
        return None
    if Path(given).is_dir():
        # Contents only (the read-only modes of an image's folders would make the copy as
        # unusable as the original), and only files the copy lacks: a command run again (a
        # health check every 30 s) copies nothing, and what numba added to the copy stays.
        shutil.copytree(given, copy, dirs_exist_ok=True, copy_function=_copy_new)
        for folder, _, files in os.walk(copy):
            os.chmod(folder, 0o700)
            for name in files:
                os.chmod(os.path.join(folder, name), 0o600)
    environ[VARIABLE] = str(copy)
    log.info("numba's cache %s is read-only: the kernels load from a copy in %s", given, copy)
    return copy


def _copy_new(source: str, target: str) -> str:
    if not os.path.exists(target):
        shutil.copyfile(source, target)
    return target
