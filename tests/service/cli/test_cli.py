"""The ``rlutf`` command line: every group's commands are registered, in their order."""

from __future__ import annotations

import argparse
import json

import pytest

from service.cli.main import build_parser, main

COMMANDS = [
    "serve",
    "config",
    "demo",
    "simulate",
    "map",
    "pose",
    "relocalize",
    "health",
    "initialpose",
    "events",
    "robots",
    "replay",
    "log",
]
ACTIONS = {
    "map": ["put", "get", "list", "remove", "import", "build", "show", "health"],
    "log": ["info", "recover", "views"],
}


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_commands_and_actions_in_order() -> None:
    commands = _subcommands(build_parser())
    assert list(commands) == COMMANDS
    for command, actions in ACTIONS.items():
        assert list(_subcommands(commands[command])) == actions


@pytest.mark.parametrize(
    "argv",
    [[c] for c in COMMANDS] + [[c, a] for c, actions in ACTIONS.items() for a in actions],
)
def test_every_command_has_help(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: rlutf {' '.join(argv)}")


def test_no_command_prints_help_and_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


def test_map_without_an_action_says_which_and_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["map"]) == 2
    assert (
        "choose an action: put, get, list, remove, import, build, show" in capsys.readouterr().err
    )


def test_log_without_an_action_prints_its_help_and_exits_2(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["log"]) == 2
    assert "usage: rlutf log" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("near", "says"),
    [
        ("1,2", "three numbers"),
        ("1,2,3,4", "three numbers"),
        ("a,b,c", "three numbers"),
        ("1,2,0", "RADIUS must be > 0"),
        ("1,2,-1", "RADIUS must be > 0"),
        ("nan,2,1", "finite"),
        ("1,inf,1", "finite"),
    ],
)
def test_relocalize_rejects_a_bad_region(
    near: str, says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["relocalize", "r1", "--map", "m", "--near", near])
    assert exit_.value.code == 2
    assert says in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["r 1", "--map", "m"], ["r1", "--map", "m/2"]])
def test_relocalize_rejects_bad_ids_before_connecting(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    # The connect endpoint is unreachable: an id error must be reported before any connection.
    assert main(["relocalize", *argv, "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "invalid" in capsys.readouterr().err


def test_relocalize_needs_a_map(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["relocalize", "r1"])
    assert exit_.value.code == 2
    assert "--map" in capsys.readouterr().err


def test_the_pose_state_follows_the_store_unless_given(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("RLUTF_SETTINGS", raising=False)

    def config(*argv: str) -> dict[str, object]:
        assert main(["config", *argv]) == 0
        return dict(json.loads(capsys.readouterr().out))

    got = config()
    assert (got["state_dir"], got["no_state"]) == ("store/state", False)
    assert (got["state_interval_s"], got["resume_max_age_s"]) == (1.0, 300.0)
    assert config("--store", "/srv/maps")["state_dir"] == "/srv/maps/state"
    assert config("--store", "/srv/maps", "--state", "/srv/state")["state_dir"] == "/srv/state"
    assert config("--no-state")["no_state"] is True
    monkeypatch.setenv("RLUTF_STORE_DIR", "/data/store")
    assert config()["state_dir"] == "/data/store/state"
    monkeypatch.setenv("RLUTF_RESUME_MAX_AGE_S", "60")
    assert config()["resume_max_age_s"] == 60.0


@pytest.mark.parametrize(
    ("argv", "attr", "value"),
    [
        (["initialpose", "r1", "--map", "m", "--pose", "-1.5,2.0,0.3"], "pose", (-1.5, 2.0, 0.3)),
        (["initialpose", "r1", "--map", "m", "--pose", "-1,-2,-0.5"], "pose", (-1.0, -2.0, -0.5)),
        (["initialpose", "r1", "--pose", "-.5,0,0", "--map", "m"], "pose", (-0.5, 0.0, 0.0)),
        (["relocalize", "r1", "--map", "m", "--near", "-4,-2.5,3"], "near", (-4.0, -2.5, 3.0)),
    ],
)
def test_negative_numbers_are_read_as_typed(
    argv: list[str], attr: str, value: tuple[float, ...]
) -> None:
    from service.cli.main import _join_number_lists

    args = build_parser().parse_args(_join_number_lists(argv))
    assert getattr(args, attr) == value
