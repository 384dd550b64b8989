"""docs/cli.md names every command of ``rlutf`` (each subcommand and each action of ``map`` and
``log``), so that a command added to the parser is not missing from the page."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.main import build_parser

PAGE = Path(__file__).resolve().parents[3] / "docs" / "cli.md"


def _commands(parser: argparse.ArgumentParser, prefix: str = "rlutf") -> list[str]:
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                inner = _commands(sub, f"{prefix} {name}")
                found += inner or [f"{prefix} {name}"]
    return found


def test_the_page_names_every_command() -> None:
    commands = _commands(build_parser())
    assert "rlutf serve" in commands and "rlutf map import" in commands
    page = PAGE.read_text(encoding="utf-8")
    missing = [c for c in commands if f"| `{c}` |" not in page]
    assert not missing, f"commands missing from the table in docs/cli.md: {missing}"
