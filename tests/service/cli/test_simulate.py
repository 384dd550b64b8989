"""``rlutf simulate`` against a real service on loopback."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from service_harness import Collector, running_bench

from service.cli.main import main
from service.live.sessions import free_port

pytestmark = pytest.mark.integration


def test_simulated_robots_are_localized_and_their_bad_input_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        poses = Collector()
        sub = bench.client.declare_subscriber("rlutf/robots/*/pose", poses)
        args = ["simulate", "-e", bench.endpoint, "--robots", "2", "--duration", "3"]
        args += ["--beams", "180", "--bad-input-every", "1", "--report-every", "1"]
        assert main(args) == 0
        sub.undeclare()
        health = bench.service.health()
        out, err = capsys.readouterr()
    assert "no rlutf service answers" not in err
    for robot in ("r000", "r001"):
        got = poses.on(f"rlutf/robots/{robot}/pose")
        assert len(got) >= 20, robot
        assert got[-1]["map_id"] == "sim"
    assert "2 of 2 robots localized" in out
    assert "bad input from r000 every 1 s" in out
    # one bad scan a second for 3 s, each refused by the service and counted
    assert b'"rejected":3' in health or b'"rejected": 3' in health


def test_robots_without_an_initial_pose_wait(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        args = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "2"]
        assert main([*args, "--beams", "90", "--no-initial-pose"]) == 0
    out = capsys.readouterr().out
    assert "initial poses: none" in out
    assert "0 of 1 robots localized" in out
    assert "not_initialized" in out  # the service's Events, as the robots see them


def test_scans_of_too_few_returns_are_not_taken_for_a_service_that_is_not_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 3 beams: under min_returns, every scan lost with an Event and no pose; the tool asked
    # whether `rlutf serve` was running while it was answering.
    with running_bench(tmp_path) as bench:
        args = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "2"]
        assert main([*args, "--beams", "3"]) == 1
    err = capsys.readouterr().err
    assert "though the service answered the robots with Events (lost" in err
    assert "is `rlutf serve` running" not in err


def test_only_the_fleets_own_events_are_counted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Another robot's Events on the bus (a broken client beside the fleet) were counted in the
    progress lines as the fleet's: here its invalid_message beside the fleet's not_initialized."""
    with running_bench(tmp_path) as bench:
        theirs = Collector()
        sub = bench.client.declare_subscriber("rlutf/robots/other1/events", theirs)
        stop = threading.Event()

        def broken_client() -> None:
            while not stop.wait(0.2):
                bench.client.put("rlutf/robots/other1/scan", b"not json")

        thread = threading.Thread(target=broken_client)
        thread.start()
        try:
            args = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "3"]
            assert main([*args, "--beams", "90", "--no-initial-pose", "--report-every", "1"]) == 0
        finally:
            stop.set()
            thread.join()
        sub.undeclare()
    out = capsys.readouterr().out
    assert any(e.get("code") == "invalid_message" for e in theirs.on("rlutf/robots/other1/events"))
    assert "not_initialized" in out  # r000's own
    assert "invalid_message" not in out, out


def test_robots_drive_a_stored_map(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with running_bench(tmp_path) as bench:
        bench.put_map("m1")
        stored = Collector()
        assert stored.wait_for(lambda: any(r.ok for r in bench.client.get("rlutf/maps/m1")))
        args = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "2"]
        assert main([*args, "--beams", "90", "--map", "m1", "--stored-map"]) == 0
        out = capsys.readouterr().out
        assert "map m1: the stored one" in out and "1 of 1 robots localized" in out
        assert main([*args, "--map", "nothere", "--stored-map"]) == 1
        assert "no valid map 'nothere' in the store" in capsys.readouterr().err


def test_a_second_fleet_of_the_same_names_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Two simulations side by side (one per map, say) with the default names would be one set
    # of robots to the service, each localized from both fleets' scans.
    with running_bench(tmp_path) as bench:
        poses = Collector()
        sub = bench.client.declare_subscriber("rlutf/robots/*/pose", poses)
        first = ["simulate", "-e", bench.endpoint, "--robots", "2", "--duration", "8"]
        done: list[int] = []
        thread = threading.Thread(target=lambda: done.append(main([*first, "--beams", "90"])))
        thread.start()
        assert poses.wait_for(lambda: poses.on("rlutf/robots/r001/pose"), timeout=30)
        second = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "2"]
        assert main([*second, "--beams", "90", "--map", "other"]) == 2
        err = capsys.readouterr().err
        assert "robots r000 (map sim) already drive on this bus" in err
        assert "--names PREFIX" in err
        assert main([*second, "--beams", "90", "--map", "other", "--names", "b"]) == 0
        assert poses.on("rlutf/robots/b000/pose")[-1]["map_id"] == "other"
        thread.join(30)
        sub.undeclare()
    assert done == [0]
    # the first fleet's robots stayed on their map
    assert {p["map_id"] for p in poses.on("rlutf/robots/r000/pose")} == {"sim"}


def test_another_seed_puts_its_building_as_the_next_version(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each --seed draws another building under the map id ``sim``: put as version 1 again, the
    store kept the first (the same version with other walls changes nothing) and every robot of
    the second run was lost on it, while simulate said "put"."""
    with running_bench(tmp_path) as bench:
        args = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "2"]
        args += ["--beams", "90"]
        assert main([*args, "--seed", "1"]) == 0
        assert "map sim: version 1 put" in capsys.readouterr().out
        assert main([*args, "--seed", "2"]) == 0
        out = capsys.readouterr().out
        assert "map sim: version 2 put" in out and "1 of 1 robots localized" in out, out
        row = next(line for line in out.splitlines() if line.startswith("r000"))
        assert float(row.split()[2]) < 5.0, out  # RMSE cm: on the walls its scans see
        assert main([*args, "--seed", "2"]) == 0
        assert "map sim: version 2 (held already)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (["--rate", "0"], "--rate must be a number above 0, got 0.0"),
        (["--robots", "0"], "--robots must be at least 1"),
        (["--map", "a/b"], "--map 'a/b' is not a map id"),
        (["--names", "a/"], "--names 'a/' does not make robot ids"),
        (["--ros2", "--relocalize-every", "2"], "ROS 2 robots have no Relocalize topic"),
    ],
)
def test_bad_flags_are_named(
    flags: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["simulate", *flags]) == 2
    assert says in capsys.readouterr().err


def test_a_fleet_on_a_prefix_no_service_uses_is_warned_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The service on one prefix, the robots on another: they got no pose for the whole run,
    and were told so only at its end."""
    with running_bench(tmp_path) as bench:
        args = ["simulate", "-e", bench.endpoint, "--robots", "1", "--duration", "1"]
        assert main([*args, "--beams", "90", "--prefix", "site2"]) == 1
    err = capsys.readouterr().err
    first, *_ = err.splitlines()
    assert "no rlutf service answers on prefix 'site2'" in first, err
    assert "no pose came back" in err


def test_no_service_says_what_to_do(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "-e", f"tcp/127.0.0.1:{free_port()}", "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert "is `rlutf serve` running? name its endpoint with -e/--connect" in err
    assert ".rs:" not in err  # no Rust source path


def test_help_explains_the_command() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "service", "simulate", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for flag in ("--duration", "--no-initial-pose", "--stored-map", "--bad-input-every", "--ros2"):
        assert flag in out


def test_sigterm_stops_the_fleet_with_its_summary(tmp_path: Path) -> None:
    """SIGTERM (``timeout``, ``docker stop``, systemd) stops the robots as Ctrl-C does: the
    summary, exit 0. It ended the process at once with no summary (exit -15) before."""
    with running_bench(tmp_path) as bench:
        cmd = [sys.executable, "-m", "service", "simulate", "-e", bench.endpoint]
        cmd += ["--robots", "1", "--duration", "120", "--beams", "90", "--report-every", "1"]
        out = tmp_path / "out.txt"
        with out.open("wb") as sink:
            proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT)
        try:
            end = time.monotonic() + 60.0
            while "1 of 1 robots localized" not in out.read_text():
                assert proc.poll() is None and time.monotonic() < end, out.read_text()
                time.sleep(0.2)
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(30.0)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    text = out.read_text()
    assert code == 0, text
    assert "interrupted: stopping the robots" in text, text
    assert "r000" in text.split("interrupted: stopping the robots")[-1], text
