"""docs/cli.md names every command of ``rlutf`` (each subcommand and each action of ``map`` and
``log``) and each command's own flags, so that a command or a flag added to the parser is not
missing from the page."""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

from service.cli.main import _join_number_lists, build_parser

PAGE = Path(__file__).resolve().parents[3] / "docs" / "cli.md"


def _parsers(
    parser: argparse.ArgumentParser, prefix: str = "rlutf"
) -> list[tuple[str, argparse.ArgumentParser]]:
    """Every command of ``parser`` (``rlutf map put``, ...) with its own parser."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                inner = _parsers(sub, f"{prefix} {name}")
                found += inner or [(f"{prefix} {name}", sub)]
    return found


def _commands(parser: argparse.ArgumentParser) -> list[str]:
    return [name for name, _ in _parsers(parser)]


def test_the_page_names_every_command() -> None:
    commands = _commands(build_parser())
    assert "rlutf serve" in commands and "rlutf map import" in commands
    page = PAGE.read_text(encoding="utf-8")
    missing = [c for c in commands if f"| `{c}` |" not in page]
    assert not missing, f"commands missing from the table in docs/cli.md: {missing}"


#: Flags the page gives once for every command (or every command on the bus), not per row.
SHARED = {"-h", "--help", "--log-level", "--debug", "-m", "--mode", "-l", "--listen", "-e"}
SHARED |= {"--connect", "-c", "--config", "--prefix"}


def test_each_row_names_the_commands_own_flags() -> None:
    """`rlutf config --help` had --processes and its row in the table did not."""
    rows = {
        line.split(" | ")[0].strip("| `"): line.split(" | ")[-1]
        for line in PAGE.read_text(encoding="utf-8").splitlines()
        if line.startswith("| `rlutf ")
    }
    missing = []
    for name, sub in _parsers(build_parser()):
        listed = set(re.findall(r"`(-{1,2}[\w-]+)", rows.get(name, "")))
        for action in sub._actions:
            own = [o for o in action.option_strings if o not in SHARED]
            if own and action.help != argparse.SUPPRESS and not listed & set(own):
                missing.append(f"{name}: {'/'.join(own)}")
    assert not missing, "flags missing from the table in docs/cli.md:\n" + "\n".join(missing)


ROOT = PAGE.parents[1]


def _shown() -> list[tuple[str, str]]:
    """Every ``rlutf ...`` command in a ``bash`` block of README.md and docs/*.md, by page."""
    found = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        blocks = re.findall(r"```bash\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)
        for block in blocks:
            for line in block.replace("\\\n", " ").splitlines():
                code = " ".join(shlex.split(line, comments=True))
                parts = code.replace("&&", ";").replace("&", ";").split(";")
                found += [(page.name, p.strip()) for p in parts if p.strip().startswith("rlutf ")]
    return found


def test_every_command_shown_in_the_docs_parses() -> None:
    shown = _shown()
    assert any("rlutf initialpose" in c for _, c in shown), "no command found in the pages"
    parser = build_parser()
    refused = []
    for page, command in shown:
        words = shlex.split(command)[1:]
        try:
            args = parser.parse_args(_join_number_lists(words))
        except SystemExit as done:
            if done.code != 0:  # 0: --version or --help, which exit after printing
                refused.append(f"{page}: {command}")
            continue
        if args.command is None:
            refused.append(f"{page}: {command} (no command)")
    assert not refused, "commands in the docs that rlutf refuses:\n" + "\n".join(refused)
