"""The repository stands alone: no test, benchmark, document or script reads or points at
anything beside it (the data the project was developed with lives in ``bench/data``, the wire
contract in ``docs/wire.md``). CI proves it by running the suite in a fresh clone; this test
names the file and line that would break that clone."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Outside a git checkout: what .gitignore leaves out (caches, environments, outputs).
SKIP = {
    ".git",
    ".venv",
    "venv",
    "__pycache__",
    ".hypothesis",
    "build",
    "dist",
    "logs",
    "store",
    "out",
}
TEXT = {".py", ".md", ".toml", ".yaml", ".yml", ".json5", ".sh", ".cfg", ".txt", ""}
#: Paths that lead out of a clone: the folder the project was specified in, or this machine's.
OUTSIDE = re.compile(r"\.\./" + r"shared\b|\bshared/(data|WIRE|DESIGN|STYLE)|/work" + r"/")


def _files() -> list[Path]:
    """The repository's files: those git tracks, else every file but the ignored kinds."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True, timeout=60
        ).stdout.decode()
        paths = [REPO / name for name in listed.split("\0") if name]
    except (OSError, subprocess.SubprocessError):
        paths = [p for p in REPO.rglob("*") if not SKIP & set(p.relative_to(REPO).parts)]
    return [
        p
        for p in sorted(paths)
        if p.is_file() and p.suffix in TEXT and p.stat().st_size < 1_000_000
    ]


def test_nothing_points_outside_the_repository() -> None:
    found = [
        f"{path.relative_to(REPO)}:{n}: {line.strip()}"
        for path in _files()
        for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not found, "\n".join(found)


def test_the_data_and_the_contract_are_here() -> None:
    data = REPO / "bench" / "data"
    for name in ("maps/depot.yaml", "maps/tb3_sandbox.yaml", "carmen/intel-corrected.log.gz"):
        assert (data / name).is_file(), name
    assert "(docs/wire.md)" in (REPO / "README.md").read_text(encoding="utf-8")
