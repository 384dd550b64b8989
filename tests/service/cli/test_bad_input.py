"""Every command, given input it cannot use, answers in a few lines that name the file or flag,
exits non-zero and prints no traceback.

The table runs the real command line in this process (``main``); a few rows run the installed
console script in a subprocess, as an operator would.
"""

from __future__ import annotations

import json
import os
import resource
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import pytest
from yaml_laughs import laughs

from bench.scenarios import DATA
from service.cli.main import main

#: Nothing listens here: every client command must say how to reach the service.
NOWHERE = "tcp/127.0.0.1:1"


class Bad(NamedTuple):
    argv: list[str]
    code: int
    says: list[str]  # each must appear in stderr


@pytest.fixture(autouse=True)
def _no_settings_file(monkeypatch: pytest.MonkeyPatch) -> None:
    # load_settings hands --settings to its sources through RLUTF_SETTINGS; set first, so that
    # monkeypatch restores the variable's absence after each test.
    monkeypatch.setenv("RLUTF_SETTINGS", "")
    monkeypatch.delenv("RLUTF_SETTINGS")


@pytest.fixture
def files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.yaml").write_text("mode: router\n  listen: [a\n")
    (tmp_path / "bad.json").write_text('{"mode": "router",\n "workers": }\n')
    (tmp_path / "bad.toml").write_text('mode = "router"\nworkers = \n')
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    (tmp_path / "unknown.yaml").write_text("modee: router\n")
    (tmp_path / "store-list.yaml").write_text("store_dir: [a, b]\n")  # a TypeError before
    # a key twice: the last silently won in YAML and JSON (TOML's reader refused it)
    (tmp_path / "twice.yaml").write_text("record_dir: a\nworkers: 0\nrecord_dir: b\n")
    (tmp_path / "twice-nested.yaml").write_text("ros2:\n  map_id: a\n  map_id: b\n")
    (tmp_path / "twice.json").write_text('{"record_dir": "a", "record_dir": "b"}')
    (tmp_path / "x.ini").write_text("[a]\n")
    (tmp_path / "corrupt.json").write_text('{"map_id": \n')
    (tmp_path / "corrupt.mcap").write_bytes(b"garbage\x00\x01")
    (tmp_path / "foreign.txt").write_text("hello\n")
    (tmp_path / "foreign.yaml").write_text("image: x.pgm\nresolution: 0.05\n")
    # a few hundred bytes whose aliases repeat a value 9 ** 10 times (tests/service/test_yamlfile)
    (tmp_path / "laughs.yaml").write_text(laughs(then="localizer: *a9\n"))
    (tmp_path / "broken-map.yaml").write_text("image: x.pgm\nresolution: [0.05\n")
    (tmp_path / "laughs-map.yaml").write_text(laughs(then="image: x.pgm\norigin: *a9\n"))
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)  # past the parser's depth
    (tmp_path / "deep.toml").write_text("a = " + "[" * 100_000 + "]" * 100_000)
    (tmp_path / "dangling").symlink_to(tmp_path / "gone")
    (tmp_path / "folder").mkdir()
    os.mkfifo(tmp_path / "pipe.yaml")  # nothing writes to it: reading it would wait for ever
    with open(tmp_path / "huge.yaml", "wb") as huge:  # 17 MiB of zeros, none on the disk
        huge.truncate(17 << 20)
    return tmp_path


def _cases() -> Iterator[Bad]:
    # settings files, in each format, named with the line
    for name, line in (("bad.yaml", 2), ("bad.json", 2), ("bad.toml", 2)):
        yield Bad(["config", "--settings", name], 2, [name, f"line {line}", "not valid"])
    yield Bad(["serve", "--settings", "bad.yaml"], 2, ["bad.yaml", "line 2"])
    yield Bad(["config", "--settings", "list.yaml"], 2, ["list.yaml", "holds a list"])
    yield Bad(["config", "--settings", "unknown.yaml"], 2, ["modee", "unknown setting"])
    for name, says in (
        ("twice.yaml", ["twice.yaml, line 3", "'record_dir' twice"]),
        ("twice-nested.yaml", ["line 3", "'map_id' twice"]),
        ("twice.json", ["twice.json", "'record_dir' twice"]),
    ):
        yield Bad(["config", "--settings", name], 2, says)
    # a store folder of the wrong type: named, not an "unexpected error" (its default state_dir)
    yield Bad(["config", "--settings", "store-list.yaml"], 2, ["store_dir", "not a valid path"])
    yield Bad(["serve", "--settings", "store-list.yaml"], 2, ["store_dir", "['a', 'b']"])
    yield Bad(["config", "--settings", "missing.yaml"], 2, ["missing.yaml", "not found"])
    yield Bad(["config", "--settings", "folder"], 2, ["folder", "is not a regular file"])
    yield Bad(["config", "--settings", "pipe.yaml"], 2, ["pipe.yaml", "not a regular file"])
    yield Bad(["config", "--settings", "x.ini"], 2, ["x.ini", ".yaml"])
    # read whole (twice: checked, then by the settings library) before it was refused
    yield Bad(["config", "--settings", "huge.yaml"], 2, ["huge.yaml", "larger than 16,777,216"])
    # zenoh's own config file
    yield Bad(["pose", "-c", "corrupt.json"], 2, ["corrupt.json", "line 2", "-c/--config"])
    yield Bad(["serve", "-c", "corrupt.json"], 2, ["corrupt.json", "line 2"])
    # not an endpoint, with no config file: the flag and the value, not "config file None"
    endpoint = ["not a zenoh endpoint", "PROTOCOL/HOST:PORT"]
    yield Bad(["serve", "-l", "bogus"], 2, ["-l/--listen bogus", *endpoint, "tcp/0.0.0.0:7447"])
    yield Bad(["health", "-e", "bogus"], 2, ["-e/--connect bogus", *endpoint, "tcp/127.0.0.1"])
    yield Bad(["simulate", "-e", "bogus"], 2, ["-e/--connect bogus", *endpoint])
    yield Bad(["pose", "-c", "corrupt.json", "-e", "bogus"], 2, ["-e/--connect bogus"])
    # out-of-range numbers and malformed values, named by flag
    yield Bad(["demo", "--rate", "0"], 2, ["--rate", "more than 0"])
    yield Bad(["demo", "--robots", "0"], 2, ["--robots", "at least 1"])
    yield Bad(["demo", "--port", "70000"], 2, ["--port", "at most 65535"])
    yield Bad(["demo", "--duration", "nan"], 2, ["--duration", "finite"])
    yield Bad(["demo", "--beams", "9000"], 2, ["--beams", "at most 8192"])  # the wire's limit
    # numpy's generators take no negative seed; the ROS 2 wire carries it in 64 bits
    yield Bad(["demo", "--seed", "-1"], 2, ["--seed", "-1", "at least 0"])
    yield Bad(["simulate", "--seed", "-1", "-e", NOWHERE], 2, ["--seed", "at least 0"])
    yield Bad(["simulate", "--seed", str(2**64), "-e", NOWHERE], 2, ["--seed", str(2**64 - 1)])
    # the range serve takes (ROS 2's on Linux), refused alike by the robots that join it
    yield Bad(["serve", "--ros-domain-id", "999"], 2, ["--ros-domain-id", "999", "at most 232"])
    yield Bad(
        ["simulate", "--ros2", "--ros-domain-id", "999", "-e", NOWHERE],
        2,
        ["--ros-domain-id", "999", "at most 232"],
    )
    yield Bad(["simulate", "--ros-domain-id", "-1", "-e", NOWHERE], 2, ["at least 0"])
    # a whole number past a float's range: named, not an OverflowError
    yield Bad(["serve", "--processes", "9" * 400], 2, ["--processes", "at most 64"])
    # a fleet whose precomputed scans would not fit in memory: refused before any is drawn
    yield Bad(["demo", "--robots", "100000"], 2, ["100000 robots", "GB", "--robots"])
    yield Bad(["simulate", "--robots", "100000", "-e", NOWHERE], 2, ["GB", "--path-seconds"])
    yield Bad(["serve", "--metrics-port", "-1"], 2, ["--metrics-port", "at least 0"])
    yield Bad(["serve", "--workers", "two"], 2, ["--workers", "whole number"])
    # a metrics address that does not resolve, or is another host's: named before any start
    for addr in ("999.1.1.1", "192.0.2.1"):
        argv = ["serve", "--metrics-addr", addr, "--metrics-port", "0"]
        yield Bad(argv, 2, [f"--metrics-addr {addr}", "not an address of this host"])
        # the live view's: exit 1 and "choose another --foxglove-port" before
        argv = ["serve", "--foxglove-addr", addr, "--foxglove-port", "0", "--processes", "0"]
        yield Bad(argv, 2, [f"--foxglove-addr {addr}", "not an address of this host"])
    yield Bad(["serve", "--processes", "65"], 2, ["--processes", "at most 64"])
    # a layout whose processes would not fit in memory (robots meant): refused before any starts
    yield Bad(["serve", "--workers", "100000"], 2, ["--workers 100000", "GB", "usable here"])
    yield Bad(["demo", "--workers", "100000"], 2, ["--workers 100000", "GB", "usable here"])
    yield Bad(
        ["serve", "--processes", "2", "--foxglove-port", "8765", "--no-record"],
        2,
        ["--foxglove-port", "--processes 0"],
    )
    yield Bad(["pose", "--timeout", "0"], 2, ["--timeout", "more than 0"])
    yield Bad(["robots", "--timeout", "soon"], 2, ["--timeout", "not a number"])
    yield Bad(["map", "health", "depot", "--timeout", "-1"], 2, ["--timeout", "more than 0"])
    yield Bad(["map", "health", "depot", "--timeout", "nan"], 2, ["--timeout", "finite"])
    yield Bad(["map", "health", "depot", "--timeout", "inf"], 2, ["--timeout", "finite"])
    yield Bad(["events", "--seconds", "-1"], 2, ["--seconds"])
    # an instance name is an id (or * for all), as `serve --instance` takes it
    for name in ("", "a/b", "**", "x" * 65):
        yield Bad(["health", "--instance", name, "-e", NOWHERE], 2, ["instance", repr(name)])
    # waits past what a clock or zenoh can time: refused, not an unexpected error (and not
    # after an initial pose or a relocalization was put)
    for argv in (
        ["events", "--seconds", "1e10"],
        ["pose", "--timeout", "1e300"],
        ["robots", "--timeout", "1e20"],
        ["health", "--timeout", "1e20"],
        ["map", "list", "--timeout", "1e20"],
        ["map", "put", "foreign.txt", "--timeout", "1e20"],
        ["map", "health", "depot", "--timeout", "1e20"],
        ["initialpose", "r1", "--map", "m", "--pose", "1,2,3", "--wait", "1e10"],
        ["relocalize", "r1", "--map", "m", "--wait", "1e10"],
    ):
        yield Bad([*argv, "-e", NOWHERE], 2, [argv[-2], "at most"])
    yield Bad(["replay", "corrupt.json", "--jobs", "-1"], 2, ["--jobs", "at least 0"])
    yield Bad(["relocalize", "r1", "--map", "m", "--wait", "-1"], 2, ["--wait"])
    yield Bad(["initialpose", "r1", "--map", "m", "--pose", "1,2"], 2, ["--pose", "X,Y,THETA"])
    yield Bad(["initialpose", "r1", "--map", "m", "--pose", "nan,1,2"], 2, ["--pose", "finite"])
    yield Bad(["initialpose", "r 1", "--map", "m", "--pose", "1,2,3"], 2, ["robot id", "'r 1'"])
    yield Bad(["events", "r/1", "-e", NOWHERE], 2, ["robot id"])
    yield Bad(["map", "remove", "m/1", "-e", NOWHERE], 2, ["map id"])
    # output paths that cannot be written, named before any work or connection
    yield Bad(["map", "get", "m1", "--out", "/missing/dir/x.json", "-e", NOWHERE], 2, ["--out"])
    yield Bad(["map", "show", "corrupt.json", "--out", "no/dir/x.png"], 2, ["--out", "no/dir"])
    yield Bad(["map", "import", "foreign.yaml", "--out", "no/dir/m.json"], 2, ["--out"])
    yield Bad(["map", "build", "foreign.txt", "--png", "no/dir/m.png"], 2, ["--png"])
    yield Bad(["serve", "--store", "foreign.txt/maps"], 2, ["--store", "not a folder"])
    yield Bad(["serve", "--record", "foreign.txt/logs"], 2, ["--record", "not a folder"])
    yield Bad(["demo", "--record", "foreign.txt"], 2, ["--record", "not a folder"])
    yield Bad(["serve", "--state", "foreign.txt/state"], 2, ["--state", "not a folder"])
    # folders the checks allow and the file system does not (a read-only one; here a name
    # longer than any file system takes, and a link to nothing on the way)
    yield Bad(["serve", "--store", "s" * 300], 2, ["--store", "cannot create the folder"])
    yield Bad(["serve", "--record", "dangling/logs"], 2, ["--record", "cannot create the folder"])
    # missing, corrupt or foreign files
    yield Bad(["map", "put", "missing.json", "-e", NOWHERE], 2, ["missing.json"])
    yield Bad(["map", "put", "folder", "-e", NOWHERE], 2, ["folder: is a folder, not a file"])
    yield Bad(["map", "put", "foreign.txt", "--timeout", "-1"], 2, ["--timeout", "at least 0"])
    yield Bad(["map", "put", "foreign.txt", "--id", "", "-e", NOWHERE], 2, ["--id", "''"])
    yield Bad(["map", "put", "foreign.txt", "--timeout", "0", "-e", NOWHERE], 2, ["--version N"])
    yield Bad(["map", "show", "folder", "-e", NOWHERE], 2, ["folder: is a folder, not a file"])
    yield Bad(["map", "show", "missing.json"], 2, ["missing.json: no such file, and not a map"])
    yield Bad(["map", "show", "corrupt.json"], 2, ["corrupt.json", "line 2", "not a map"])
    yield Bad(["map", "show", "foreign.yaml"], 2, ["rlutf map import foreign.yaml --png"])
    yield Bad(["map", "import", "missing.yaml"], 2, ["missing.yaml", "no such file"])
    yield Bad(["map", "import", "folder"], 2, ["folder", "is a folder"])
    yield Bad(["map", "build", "missing.log"], 2, ["missing.log", "no such file"])
    yield Bad(["map", "build", "folder"], 2, ["folder", "no log file"])
    yield Bad(["map", "import", "foreign.yaml"], 2, ["foreign.yaml"])
    yield Bad(["config", "--settings", "laughs.yaml"], 2, ["laughs.yaml", "100,000 values"])
    yield Bad(["map", "import", "laughs-map.yaml"], 2, ["laughs-map.yaml", "100,000 values"])
    # a map YAML that is no YAML: the parser's four-line report, no line number in its file
    # and no fix before
    yield Bad(
        ["map", "import", "broken-map.yaml"], 2, ["broken-map.yaml", "map YAML, line 3", "fix the"]
    )
    yield Bad(["config", "--settings", "deep.json"], 2, ["deep.json", "not valid JSON"])
    yield Bad(["config", "--settings", "deep.toml"], 2, ["deep.toml", "not valid TOML"])
    yield Bad(["map", "show", "deep.json"], 2, ["deep.json", "nested deeper than a map"])
    yield Bad(["map", "build", "foreign.txt"], 2, ["foreign.txt"])
    intel = str(DATA / "carmen" / "intel-corrected.log.gz")
    # flags of map build and import refused before the log or grid is read (it was after)
    for flag, value, said in (
        ("--resolution", "0", "more than 0"),
        ("--max-range", "-1", "more than 0"),
        ("--component", "abc", "'abc'"),
        ("--id", "", "invalid map id ''"),
        ("--min-area", "-1", "at least 0"),
        ("--surface-offset", "0.03", "half a cell (0.025 m"),
        ("--simplify", "0.1", "at most a cell (0.05 m"),
    ):
        yield Bad(["map", "build", intel, flag, value], 2, [flag, said])
    yield Bad(["map", "import", "foreign.yaml", "--component", "1,x"], 2, ["--component"])
    # a grid of 139 billion cells (7 TB: over half the memory of any host) is refused before
    # it is allocated, with what fits here
    yield Bad(
        ["map", "build", intel, "--resolution", "0.0001"],
        2,
        ["139,113,398,844 cells", "GB to build", "give --resolution"],
    )
    yield Bad(["log", "info", "corrupt.mcap"], 2, ["corrupt.mcap", "not an MCAP file"])
    yield Bad(["log", "info", "missing.mcap"], 2, ["missing.mcap"])
    yield Bad(["replay", "foreign.txt", "--out", "o.mcap"], 2, ["foreign.txt"])
    # no service reachable: a hint, not a Rust source path
    for argv in (
        ["pose"],
        ["health"],
        ["robots"],
        ["events"],
        ["map", "list"],
        ["map", "get", "m1"],
        ["initialpose", "r1", "--map", "m1", "--pose", "-1.5,2.0,0.3"],
        ["relocalize", "r1", "--map", "m1"],
    ):
        yield Bad([*argv, "-e", NOWHERE], 1, [NOWHERE, "is `rlutf serve` running?", "-e/--connect"])


CASES = list(_cases())


def _run(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exit_:  # argparse refuses a flag this way
        return int(exit_.code or 0)


@pytest.mark.parametrize("case", CASES, ids=[" ".join(c.argv) for c in CASES])
def test_bad_input_is_named_with_no_traceback(
    case: Bad, files: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = _run(case.argv)
    out, err = capsys.readouterr()
    assert code == case.code, err
    for text in case.says:
        assert text in err
    assert "Traceback" not in err + out
    assert ".rs:" not in err  # no Rust source path from zenoh
    assert len(err.strip().splitlines()) <= 6


def test_settings_errors_reach_client_commands_through_the_environment(
    files: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("RLUTF_SETTINGS", "bad.yaml")
    assert _run(["pose", "-e", NOWHERE]) == 2
    assert "bad.yaml, line 2" in capsys.readouterr().err


@pytest.fixture
def taken_port() -> Iterator[int]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


def test_serve_on_a_taken_port_says_so(
    taken_port: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    common = ["--store", str(tmp_path / "s"), "--no-record", "--workers", "0", "--no-state"]
    code = _run(["serve", "-l", f"tcp/127.0.0.1:{taken_port}", *common])
    err = capsys.readouterr().err
    assert code == 1
    assert f"tcp/127.0.0.1:{taken_port}" in err and "-l/--listen" in err
    assert "the port is taken" in err and ".rs:" not in err
    # not an endpoint at all: not a taken port either, and the flag's value to fix (exit 2)
    code = _run(["serve", "-l", "tcp/127.0.0.1:99999", *common])
    err = capsys.readouterr().err
    assert code == 2 and "port is taken" not in err
    assert "-l/--listen tcp/127.0.0.1:99999: port 99999 is over 65535" in err, err
    code = _run(["robots", "-e", "tcp/127.0.0.1:70000"])
    err = capsys.readouterr().err
    assert code == 2 and "-e/--connect tcp/127.0.0.1:70000: port 70000 is over 65535" in err, err

    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    code = _run(["demo", "--port", str(taken_port), "--no-record", "--workers", "0"])
    err = capsys.readouterr().err
    assert code == 1 and str(taken_port) in err and "the port is taken" in err

    code = _run(
        [
            "serve",
            "-l",
            f"tcp/127.0.0.1:{port}",
            "--metrics-addr",
            "127.0.0.1",
            "--metrics-port",
            str(taken_port),
            *common,
        ]
    )
    err = capsys.readouterr().err
    assert code == 1
    assert f"127.0.0.1:{taken_port}" in err and "--metrics-port" in err


def test_serve_with_processes_on_a_taken_metrics_port_says_which_and_what_to_do(
    files: Path,
    taken_port: int,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The default layout (a host of service processes) names the metrics port it could not
    take and the fix, as a single process does; it said "[Errno 98] Address already in use".
    Before it starts any process (it said so about 5 s later, its processes started)."""
    from service.live.host import Host

    def started(*args: object, **kw: object) -> None:
        raise AssertionError("the host started its processes")

    monkeypatch.setattr(Host, "start", started)
    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    argv = ["serve", "--processes", "2", "-l", f"tcp/127.0.0.1:{port}", "--no-record"]
    argv += ["--store", str(files / "s"), "--no-state", "--metrics-addr", "127.0.0.1"]
    code = _run([*argv, "--metrics-port", str(taken_port)])
    err = capsys.readouterr().err
    assert code == 1, err
    assert f"cannot serve metrics on 127.0.0.1:{taken_port}" in err, err
    assert "choose another --metrics-port" in err and "[Errno" not in err, err


def test_log_level_and_debug_after_the_subcommand(
    files: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _run(["config", "--log-level", "debug"]) == 0
    assert _run(["--log-level", "INFO", "config", "--log-level", "ERROR"]) == 0
    capsys.readouterr()
    with pytest.raises(Exception, match="cannot reach zenoh"):
        main(["pose", "-e", NOWHERE, "--debug"])  # --debug: the exception, traceback and all


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["--version"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("rlutf ") and "v1.2" in out


def _console_script(argv: list[str], **run: Any) -> subprocess.CompletedProcess[str]:
    """``python -m service ARGV`` in a process of its own, as the console script runs it."""
    return subprocess.run(
        [sys.executable, "-m", "service", *argv],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        **run,
    )


def _address_space(limit: int) -> None:
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


@pytest.mark.parametrize(
    "argv",
    [["demo", "--robots", "100000000"], ["simulate", "--robots", "100000000", "-e", NOWHERE]],
)
def test_a_fleet_too_big_is_refused_before_its_robots_are_named(
    files: Path, argv: list[str]
) -> None:
    """The fleet was sized after its robots' ids were made: 22 GB for 10**8 robots, until the
    kernel's OOM killer ended it (here, a process held to 1.5 GB: a MemoryError)."""
    done = _console_script(argv, preexec_fn=lambda: _address_space(1_500_000_000))
    assert done.returncode == 2, done.stderr
    assert "100000000 robots" in done.stderr and "GB" in done.stderr


def test_an_output_the_file_system_refuses_is_named_as_the_output(
    files: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """/proc passes the checks (a folder root may write in) and refuses the file: said of --out
    and --png, not 'not a map' or an unexpected error."""
    room = {"type": "Polygon", "coordinates": [[[0, 0], [6, 0], [6, 4], [0, 4], [0, 0]]]}
    (files / "room.json").write_text(json.dumps(room))
    yaml = DATA / "maps" / "tb3_sandbox.yaml"
    for argv, flag in (
        (["map", "show", "room.json", "--out", "/proc/x.png"], "--out"),
        (["map", "import", str(yaml), "--out", "t.json", "--png", "/proc/x.png"], "--png"),
        (["map", "import", str(yaml), "--out", "/proc/t.json"], "--out"),
    ):
        code = _run(argv)
        err = capsys.readouterr().err
        assert code in (1, 2), err  # 2: refused before the work where /proc is not writable
        assert f"{flag} /proc/" in err and "not a map" not in err and "unexpected" not in err


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["config", "--settings", "bad.yaml"], "bad.yaml, line 2"),
        (["demo", "--rate", "0"], "--rate"),
        (["map", "get", "m1", "--out", "/missing/dir/x.json", "-e", NOWHERE], "--out"),
        (["pose", "-e", NOWHERE], "is `rlutf serve` running?"),
    ],
)
def test_the_console_script_says_the_same(files: Path, argv: list[str], says: str) -> None:
    done = _console_script(argv)
    assert done.returncode != 0
    assert says in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize(
    ("variable", "value"),
    [("RLUTF_LOCALIZER", "garbage"), ("RLUTF_ROS2__ROBOTS", "r7"), ("RLUTF_LIMITS", "{")],
)
@pytest.mark.parametrize("argv", [["config"], ["serve"], ["pose", "-e", NOWHERE]])
def test_a_nested_setting_in_the_environment_that_is_not_json_is_named(
    files: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    variable: str,
    value: str,
    argv: list[str],
) -> None:
    """Before: "unexpected error: SettingsError: error parsing value for field ...", exit 1."""
    monkeypatch.setenv(variable, value)
    assert _run(argv) == 2
    err = capsys.readouterr().err
    assert f"{variable} in the environment is not valid JSON" in err, err
    assert "unexpected error" not in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_demo_names_a_bad_environment_value_as_serve_does(
    files: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: "rlutf demo: unexpected error: ValidationError: 1 validation error ...", exit 1."""
    monkeypatch.setenv("RLUTF_LOCALIZER__MIN_FIT", "2")
    for argv in (["demo", "--duration", "1"], ["simulate", "-e", NOWHERE], ["serve"]):
        assert _run(argv) == 2
        err = capsys.readouterr().err
        assert "invalid configuration" in err and "min_fit" in err, err
        assert "unexpected error" not in err


def test_a_read_only_file_system_is_named_as_such(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A folder on a read-only mount (a container's read-only layer) was reported as
    "permission denied", which sends an operator to chmod; the file system's own flag says
    which it is. (Mounting one needs root: the flag is given here as statvfs would give it.)"""

    from service.cli.errors import CliError
    from service.cli.flags import usable_folder, writable

    real = os.statvfs

    class ReadOnly:
        f_flag = os.ST_RDONLY

    monkeypatch.setattr(os, "access", lambda path, mode: False)
    monkeypatch.setattr(os, "statvfs", lambda path: ReadOnly())
    with pytest.raises(CliError, match=r"--state .*on a read-only file system"):
        usable_folder(tmp_path / "state", "--state")
    with pytest.raises(CliError, match=r"--out .*not writable \(on a read-only file system\)"):
        writable(tmp_path / "x.json", "--out")
    monkeypatch.setattr(os, "statvfs", real)
    with pytest.raises(CliError, match=r"--out .*\(permission denied\)"):
        writable(tmp_path / "x.json", "--out")
