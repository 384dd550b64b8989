"""numba's kernel cache on a read-only file system: copied to a writable folder first."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from service.kernelcache import VARIABLE, writable, writable_kernel_cache


def _image_cache(root: Path) -> Path:
    """A cache folder as the image's build leaves it: an index and a kernel per function."""
    cache = root / "numba"
    (cache / "rlutf_abc").mkdir(parents=True)
    (cache / "rlutf_abc" / "_kernels.cast-1.py311.nbi").write_bytes(b"index")
    (cache / "rlutf_abc" / "_kernels.cast-1.py311.1.nbc").write_bytes(b"kernel")
    return cache


def test_unset_or_writable_is_left_to_numba(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    assert writable_kernel_cache(env) is None and env == {}
    env = {VARIABLE: str(tmp_path / "cache")}
    assert writable_kernel_cache(env) is None
    assert env == {VARIABLE: str(tmp_path / "cache")} and (tmp_path / "cache").is_dir()


def test_a_read_only_cache_is_copied_where_it_can_be_written(tmp_path: Path) -> None:
    cache = _image_cache(tmp_path / "image")
    for path in [*cache.rglob("*"), cache]:  # read-only, as the image's build leaves it
        path.chmod(0o555 if path.is_dir() else 0o444)
    env = {VARIABLE: str(cache)}

    def can_write(folder: Path) -> bool:  # the image's folder is read-only
        return folder != cache and writable(folder)

    copy = writable_kernel_cache(env, tmp_path / "tmp", can_write)
    assert copy is not None and copy.parent == tmp_path / "tmp"
    assert env[VARIABLE] == str(copy)
    copied = sorted(p.relative_to(copy) for p in copy.rglob("*") if p.is_file())
    assert copied == sorted(p.relative_to(cache) for p in cache.rglob("*") if p.is_file())
    assert (copy / "rlutf_abc" / "_kernels.cast-1.py311.1.nbc").read_bytes() == b"kernel"
    for path in [copy, *copy.rglob("*")]:  # numba writes beside what it loads
        assert path.stat().st_mode & 0o200, path
    # a second start (the copy already there) takes it again, and keeps what numba wrote there
    (copy / "rlutf_abc" / "_kernels.cast-1.py311.nbi").write_bytes(b"index, one more entry")
    env = {VARIABLE: str(cache)}
    assert writable_kernel_cache(env, tmp_path / "tmp", can_write) == copy
    assert (
        copy / "rlutf_abc" / "_kernels.cast-1.py311.nbi"
    ).read_bytes() == b"index, one more entry"
    for path in [cache, *cache.rglob("*")]:  # so that pytest can remove it
        path.chmod(0o755)


def test_a_cache_path_that_cannot_be_made_goes_to_the_temporary_folder(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    env = {VARIABLE: str(blocker / "numba")}  # no folder can be made under a file
    assert not writable(blocker / "numba")
    copy = writable_kernel_cache(env, tmp_path / "tmp")
    assert copy is not None and env[VARIABLE] == str(copy) and writable(copy)


def test_nowhere_to_write_is_said(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    env = {VARIABLE: str(tmp_path / "ro")}
    with caplog.at_level(logging.WARNING):
        assert writable_kernel_cache(env, tmp_path / "tmp", lambda folder: False) is None
    assert env == {VARIABLE: str(tmp_path / "ro")}
    assert "mount a writable volume" in caplog.text


def test_every_rlutf_command_takes_a_writable_cache_first(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    env = {**os.environ, VARIABLE: str(blocker / "numba"), "TMPDIR": str(tmp_path)}
    argv = [sys.executable, "-m", "service", "--log-level", "INFO", "config"]
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "the kernels load from a copy in" in done.stderr, done.stderr
