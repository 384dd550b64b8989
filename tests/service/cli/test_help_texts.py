"""Every `rlutf` flag that has a default says it in its help, and every argument is explained.

`rlutf map build --help` listed `--scan-topic` with no default (it is `/scan`), and the
arguments of `map put`, `map get`, `map health` and `log recover` (FILE, MAP_ID, OUT) had no
help at all, where docs/cli.md promises each command's flags "with their defaults".
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from service.cli.main import build_parser


def _actions(
    parser: argparse.ArgumentParser, path: str = "rlutf"
) -> Iterator[tuple[str, argparse.Action]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _actions(sub, f"{path} {name}")
        elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            yield path, action


def test_every_flag_with_a_default_states_it() -> None:
    silent = [
        f"{path} {'/'.join(a.option_strings)} (default {a.default!r})"
        for path, a in _actions(build_parser())
        if a.option_strings
        and a.default not in (None, False, [], argparse.SUPPRESS)
        and "default" not in (a.help or "").lower()
    ]
    assert silent == []


def test_every_argument_is_explained() -> None:
    bare = [f"{path} {a.dest}" for path, a in _actions(build_parser()) if not a.help]
    assert bare == []
