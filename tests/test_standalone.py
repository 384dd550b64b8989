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


#: A Markdown link or image, ``[text](target)``; the target up to a space or the closing bracket.
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _broken_links(page: Path) -> list[str]:
    """The relative links of a Markdown page that name no file or folder of the repository."""
    broken = []
    for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        for target in LINK.findall(line):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):
                continue  # a URL (https:, mailto:)
            name, _, anchor = target.partition("#")
            path = (page.parent / name).resolve() if name else page
            if not (path.exists() and path.is_relative_to(REPO)):
                broken.append(f"{page.relative_to(REPO)}:{n}: {target}")
            elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
                broken.append(f"{page.relative_to(REPO)}:{n}: {target} (no such heading)")
    return broken


def _anchors(page: Path) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces to
    hyphens, ``-1``, ``-2`` ... on repeats."""
    count: dict[str, int] = {}
    anchors = set()
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    for heading in re.findall(r"^#{1,6} +(.+?) *#*$", text, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")
        anchors.add(f"{slug}-{count[slug]}" if slug in count else slug)
        count[slug] = count.get(slug, 0) + 1
    return anchors


def test_every_relative_link_in_the_docs_resolves() -> None:
    pages = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    assert len(pages) > 1, "docs/*.md not found"
    broken = [b for page in pages for b in _broken_links(page)]
    assert not broken, "\n".join(broken)


def test_every_docs_page_is_found_from_the_readme() -> None:
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    missing = [
        p.name for p in sorted((REPO / "docs").glob("*.md")) if f"](docs/{p.name}" not in readme
    ]
    assert not missing, f"docs pages the README does not link: {missing}"
