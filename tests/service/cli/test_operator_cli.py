"""The operator's commands against a real service on loopback: initialpose, events, pose,
health, relocalize, robots (silent and waiting robots), map list and map remove."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
import zenoh
from service_harness import JSON, Bench, Collector, SimRobot, running_bench

from schemas import encode
from service.cli.main import main

pytestmark = pytest.mark.integration


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _drive(robot: SimRobot, steps: int) -> None:
    for _ in range(steps):
        robot.advance()
        time.sleep(0.03)


def _stand(robot: SimRobot, done: threading.Event) -> None:
    """Odometry and scans of a robot standing still, stamped now (as a real robot stamps them,
    so that an operator's InitialPose, stamped now, falls among them) until ``done``."""
    while not done.is_set():
        robot.t0 = time.time_ns() - robot.step * 100_000_000
        robot.odom(robot.step)
        scan = encode(robot.scan_msg(robot.step))
        robot.session.put(f"rlutf/robots/{robot.robot_id}/scan", scan, encoding=JSON)
        time.sleep(0.05)


def _tracked(bench: Bench) -> SimRobot:
    """Robot r1 on map m1 (already put), with a few poses published."""
    col = Collector()
    sub = bench.client.declare_subscriber("rlutf/robots/r1/pose", col)
    time.sleep(0.3)
    # loaded first (on a busy host a put takes a while): scans before it would be skipped
    assert col.wait_for(lambda: bench.service.maps.get("m1") is not None)
    robot = bench.robot("r1", 1)
    robot.initial_pose("m1")
    time.sleep(0.3)
    _drive(robot, 3)
    assert col.wait_for(lambda: len(col.on("rlutf/robots/r1/pose")) >= 2)
    sub.undeclare()
    return robot


def test_initialpose_starts_a_waiting_robot_and_events_show_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        e = bench.endpoint
        code, out, _ = _cli(capsys, "robots", "-e", e)  # none yet: said, not a bare header
        assert code == 0 and out.startswith("no robots: 1 instance(s) answered"), out
        bench.put_map()
        robot = bench.robot("r1", 1)
        # scans with no initial pose: a waiting robot, and not_initialized Events
        done = threading.Event()
        standing = threading.Thread(target=_stand, args=(robot, done))
        standing.start()
        seen = [_cli(capsys, "events", "r1", "-e", e, "--seconds", "1.5")]
        done.set()
        standing.join()
        code, out, _ = seen[0]
        assert code == 0
        assert "not_initialized" in out and "rlutf initialpose r1" in out

        code, out, err = _cli(capsys, "robots", "-e", e)
        assert code == 0
        row = next(line for line in out.splitlines() if line.startswith("r1"))
        assert row.split()[:3] == ["r1", "-", "waiting"]
        assert "rlutf initialpose ROBOT" in out
        code, out, err = _cli(capsys, "pose", "-e", e, "--timeout", "1")
        assert code == 1
        assert "no robot has a pose" in err and "'*'" not in err

        # the pose as typed, negative numbers included; the robot's next scan starts it
        x, y, theta = (float(v) for v in robot.truth[robot.step])
        pose = f"{x:.4f},{y:.4f},{theta:.4f}"
        done = threading.Event()
        driver = threading.Thread(target=_stand, args=(robot, done))
        driver.start()
        code, out, err = _cli(capsys, "initialpose", "r1", "--map", "m1", "--pose", pose, "-e", e)
        done.set()
        driver.join()
        assert code == 0, err
        assert "initial pose set: r1 at x" in out
        assert "r1 on m1: tracking at" in out or "r1 on m1: corrected at" in out

        code, out, _ = _cli(capsys, "pose", "r1", "-e", e)
        assert code == 0
        header, line = out.splitlines()
        assert header.split()[:4] == ["robot", "map", "status", "x"]
        assert line.split()[:2] == ["r1", "m1"]
        assert abs(float(line.split()[3]) - float(robot.truth[robot.step][0])) < 0.2
        code, out, _ = _cli(capsys, "pose", "r1", "-e", e, "--json")
        assert json.loads(out)["robot_id"] == "r1"

        code, out, _ = _cli(capsys, "robots", "-e", e, "--json")
        (r1,) = json.loads(out)
        assert r1["status"] in ("tracking", "corrected") and r1["silent"] is False
        assert 0 < r1["sigma_xy_m"] < 1
        # no scan for a while: marked silent
        code, out, _ = _cli(capsys, "robots", "-e", e, "--silent", "0.2")
        time.sleep(0.3)
        code, out, _ = _cli(capsys, "robots", "-e", e, "--silent", "0.2")
        assert "silent (" in out.splitlines()[1]


def test_a_refused_initial_pose_is_told_what_to_mend(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A pose beyond the service's limits used to be told to check `rlutf map list`.
    with running_bench(tmp_path) as bench:
        bench.put_map()
        argv = ["initialpose", "r1", "--map", "m1", "--pose", "1e9,2,0", "-e", bench.endpoint]
        code, out, err = _cli(capsys, *argv, "--force")  # past the command's own check
        assert code == 1
        assert "invalid_message" in out and "InitialPose.x" in out
        assert "the field it names is out of what the service accepts" in err
        assert "map list" not in err


def test_a_request_refused_again_within_a_second_is_told_refused_again(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The service holds back repeated Events of one code for one robot (event_interval_s);
    # the refusal of an operator's request is never held back: the command waits for it.
    with running_bench(tmp_path, event_interval_s=1.0) as bench:
        bench.put_map()
        e = bench.endpoint
        for theta in ("1e9", "2e9"):  # the operator mends one field, not the other
            argv = ["initialpose", "r1", "--map", "m1", "--pose", f"1,2,{theta}", "-e", e]
            code, out, err = _cli(capsys, *argv, "--wait", "3")
            assert code == 1, (theta, out, err)
            assert "InitialPose.theta" in out
        for radius in ("1e9", "2e9"):
            argv = ["relocalize", "r1", "--map", "m1", "--near", f"1,2,{radius}", "-e", e]
            code, out, err = _cli(capsys, *argv, "--wait", "3")
            assert code == 1, (radius, out, err)
            assert "Relocalize.region.radius" in out


def test_an_initial_pose_far_off_the_stored_map_is_refused_before_it_is_put(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A typo (1000 for 10.00) or a pose on another map's coordinates used to be put and said
    # "no pose within 5 s"; the robot then searched the whole map from its first scan.
    with running_bench(tmp_path) as bench:
        bench.put_map()
        time.sleep(0.3)  # stored
        e = bench.endpoint
        argv = ["initialpose", "r1", "--map", "m1", "--pose", "1000,1000,0", "-e", e]
        code, out, err = _cli(capsys, *argv)
        assert code == 1 and out == ""
        assert "outside the free space of map 'm1'" in err and "--force" in err
        # an absurd number reads as one, not as its 300 digits
        absurd = ["initialpose", "r1", "--map", "m1", "--pose", "1e300,1,0", "-e", e]
        code, out, err = _cli(capsys, *absurd)
        assert code == 1 and "1e+300 m outside" in err and len(err) < 600, err
        code, out, err = _cli(capsys, *absurd[:5], "1,2,1e300", "--degrees", "--wait", "0", "-e", e)
        assert len(out + err) < 600, (out, err)
        code, out, _ = _cli(capsys, "robots", "-e", e, "--json")
        assert json.loads(out) == []  # nothing was put
        # near the map (a click into a wall): put as before
        x0, y0 = bench.world.bounds[:2]
        near = f"{x0 - 0.5},{y0 + 1.0},0"
        code, _, err = _cli(capsys, "initialpose", "r1", "--map", "m1", "--pose", near, "-e", e)
        assert code == 0 and "initial pose put" in err
        code, _, err = _cli(capsys, *argv, "--force", "--wait", "0")
        assert code == 0, err


def test_a_relocalize_circle_off_the_stored_map_is_refused_before_it_is_put(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A --near circle wholly off the map (a typo, another map's coordinates) was put: the
    # robot then searched that circle at every scan, lost for good, its Events saying
    # "relocalizing on the whole map", and the command ended "not relocalized" after --wait.
    with running_bench(tmp_path) as bench:
        bench.put_map()
        time.sleep(0.3)  # stored
        e = bench.endpoint
        argv = ["relocalize", "r1", "--map", "m1", "--near", "1000,1000,1", "-e", e]
        code, out, err = _cli(capsys, *argv, "--wait", "0")
        assert code == 1 and out == "", (out, err)
        assert "--near: the circle of 1 m around (1000, 1000)" in err, err
        assert "outside the free space of map 'm1'" in err and "leave out --near" in err, err
        code, out, _ = _cli(capsys, "robots", "-e", e, "--json")
        assert json.loads(out) == []  # nothing was put
        # a circle that reaches the map is put as before
        x0, y0 = bench.world.bounds[:2]
        reach = ["relocalize", "r1", "--map", "m1", "--near", f"{x0 - 3},{y0 + 1},3", "-e", e]
        code, out, err = _cli(capsys, *reach, "--wait", "0")
        assert code == 0 and "asked the service to relocalize r1" in out, (out, err)


def test_initialpose_on_a_missing_map_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        code, out, err = _cli(
            capsys,
            "initialpose",
            "r1",
            "--map",
            "nowhere",
            "--pose",
            "-1.5,2.0,0.3",
            "-e",
            bench.endpoint,
            "--json",
        )
        assert code == 1
        assert json.loads(out.splitlines()[0])["code"] == "map_not_found"
        assert "rlutf map list" in err
        # before any scan: listed as waiting for the map, not as placed and waiting for a scan
        code, out, _ = _cli(capsys, "robots", "-e", bench.endpoint, "--json")
        assert [(r["robot_id"], r["reason"]) for r in json.loads(out)] == [("r1", "map_not_found")]
        # its scans wait for that map: listed as waiting for it, not for an initial pose
        robot = bench.robot("r1", 1)
        robot.odom(0)
        waiting: list[dict] = []
        for _ in range(50):
            robot.advance()
            code, out, _ = _cli(capsys, "robots", "-e", bench.endpoint, "--json")
            waiting = [r for r in json.loads(out) if r["status"] == "waiting"]
            if waiting:
                break
        assert [(r["robot_id"], r["reason"]) for r in waiting] == [("r1", "map_not_found")]


def test_commands_that_need_a_service_say_when_none_is_live(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with running_bench(tmp_path) as bench:
        for argv in (
            ["initialpose", "r1", "--map", "m1", "--pose", "1,2,3"],
            ["relocalize", "r1", "--map", "m1"],
        ):
            code, _, err = _cli(capsys, *argv, "-e", bench.endpoint, "--prefix", "elsewhere")
            assert code == 1
            assert "no rlutf service is live on prefix 'elsewhere'" in err
            assert "-e/--connect" in err and "Traceback" not in err


def test_map_health_before_any_evidence_says_the_service_is_live(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A map put, no robot on it yet: the service answers no MapHealth (it has counted no scan
    # of the map). That read "no service answered", as if the service were down.
    with running_bench(tmp_path) as bench:
        bench.put_map("m1")
        time.sleep(0.3)
        code, out, err = _cli(capsys, "map", "health", "m1", "-e", bench.endpoint)
        assert code == 1 and out == "", (out, err)
        assert "no service answered" not in err and "live" in err and "'m1'" in err, err
        assert "no MapHealth for map 'm1' yet" in err, err
        # a map id no storage holds (a typo) is said so, not "counted no scan ... yet"
        code, out, err = _cli(capsys, "map", "health", "m2", "-e", bench.endpoint)
        assert code == 1 and out == "", (out, err)
        assert "no storage holds map 'm2'" in err and "rlutf map list" in err, err
        assert "yet" not in err, err
        code, _, err = _cli(capsys, "map", "health", "m1", "-e", bench.endpoint, "--prefix", "x")
        assert code == 1 and "no rlutf service is live on prefix 'x'" in err, err


def test_health_and_relocalize_read_as_text(
    bench: Bench, capsys: pytest.CaptureFixture[str]
) -> None:
    e = bench.endpoint
    code, out, _ = _cli(capsys, "health", "-e", e)
    assert code == 0
    header, line = out.splitlines()
    assert header.split()[:3] == ["instance", "ready", "up"]
    assert line.split()[0] == bench.service.settings.instance
    code, out, _ = _cli(capsys, "health", "-e", e, "--json")
    assert json.loads(out)["instance"] == bench.service.settings.instance

    bench.put_map()
    robot = _tracked(bench)
    driver = threading.Thread(target=_drive, args=(robot, 40))
    driver.start()
    code, out, err = _cli(capsys, "relocalize", "r1", "--map", "m1", "-e", e, "--wait", "8")
    driver.join()
    assert code == 0, err
    lines = out.splitlines()
    assert any("relocalizing:" in line for line in lines)
    assert lines[-1].startswith("r1 on m1: ")  # the pose it was relocalized at, or a later one
    assert not any(line.startswith("{") for line in lines)  # no raw JSON by default


def test_map_list_and_remove(bench: Bench, capsys: pytest.CaptureFixture[str]) -> None:
    e = bench.endpoint
    bench.put_map("m1")
    bench.put_map("m2", version=3)
    _tracked(bench)

    code, out, _ = _cli(capsys, "map", "list", "-e", e, "--json")
    assert code == 0
    rows = {m["map_id"]: m for m in json.loads(out)}
    assert set(rows) == {"m1", "m2"}
    assert (rows["m1"]["version"], rows["m2"]["version"]) == (1, 3)
    assert rows["m1"]["robots"] == ["r1"] and rows["m2"]["robots"] == []
    assert rows["m1"]["size_bytes"] == (bench.store / "m1.json").stat().st_size
    assert all(0 < v < 1000 for v in rows["m1"]["extent_m"])
    code, out, _ = _cli(capsys, "map", "list", "-e", e)
    assert [line.split()[0] for line in out.splitlines()] == ["map", "m1", "m2"]
    assert out.splitlines()[1].split()[-1] == "r1"

    # a map robots are on needs --force; an unused one goes; an unknown one is named
    code, _, err = _cli(capsys, "map", "remove", "m1", "-e", e)
    assert code == 1 and "robots are on map 'm1': r1" in err and "--force" in err
    code, out, err = _cli(capsys, "map", "remove", "m2", "-e", e)
    assert code == 0, err
    assert "removed map m2" in out
    assert not (bench.store / "m2.json").exists()
    code, _, err = _cli(capsys, "map", "remove", "m2", "-e", e)
    assert code == 1 and "no storage holds map 'm2'" in err
    code, out, _ = _cli(capsys, "map", "list", "-e", e, "--json")
    assert [m["map_id"] for m in json.loads(out)] == ["m1"]
    code, _, _ = _cli(capsys, "map", "remove", "m1", "-e", e, "--force")
    assert code == 0
    # the store empty, the service live (a site's first day): an empty list, and how to fill it
    # (it said "no storage answered with a map", exit 1, as if the service were down)
    code, out, err = _cli(capsys, "map", "list", "-e", e)
    assert code == 0 and "no maps stored yet" in err and "rlutf map put" in err, err


def test_map_list_and_remove_count_the_robots_placed_on_a_map_with_no_pose_yet(
    bench: Bench, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot given an initial pose on a map and no scan since has no pose, yet the service
    holds it on that map (it waits for its first scan): `map list` did not show it and `map
    remove` took the map away without --force, so that its first scan ran on the service's copy
    of a map no store held any more."""
    e = bench.endpoint
    bench.put_map("m1")
    assert Collector().wait_for(lambda: bench.service.maps.get("m1") is not None)
    bench.robot("r2", 2).initial_pose("m1")
    assert Collector().wait_for(
        lambda: [w.robot_id for w in bench.service.robot_view.waiting()] == ["r2"]
    )
    code, out, _ = _cli(capsys, "map", "list", "-e", e, "--json")
    assert code == 0 and [(m["map_id"], m["robots"]) for m in json.loads(out)] == [("m1", ["r2"])]
    code, _, err = _cli(capsys, "map", "remove", "m1", "-e", e)
    assert code == 1 and "robots are on map 'm1': r2" in err and "--force" in err, err
    assert (bench.store / "m1.json").exists()


def test_map_put_with_timeout_0_is_put_unconfirmed_and_map_show_reads_paths_as_files(
    bench: Bench, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """--timeout 0 waits for nothing: the map is put and said to be unconfirmed (it was said
    that nothing holds it, exit 1, while the store held it). A folder given to map show is
    refused as one, not asked for as a map id."""
    e = bench.endpoint
    path = tmp_path / "hall.json"
    path.write_text(
        json.dumps({"type": "Polygon", "coordinates": [[[0, 0], [6, 0], [6, 4], [0, 4], [0, 0]]]})
    )
    code, out, err = _cli(
        capsys, "map", "put", str(path), "--version", "2", "--timeout", "0", "-e", e
    )
    assert code == 0, err
    assert "put rlutf/maps/hall (version 2" in out and "not confirmed, --timeout 0" in out
    assert "nothing holds it" not in err
    deadline = time.monotonic() + 10.0
    while not (bench.store / "hall.json").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert json.loads((bench.store / "hall.json").read_text())["version"] == 2
    # next needs the store's answer, which --timeout 0 does not wait for: refused, nothing put
    code, _, err = _cli(capsys, "map", "put", str(path), "--id", "other", "--timeout", "0", "-e", e)
    assert code == 2 and "--version N" in err
    assert not (bench.store / "other.json").exists()
    (tmp_path / "hall").mkdir()
    code, _, err = _cli(capsys, "map", "show", str(tmp_path / "hall"), "-e", e)
    assert code == 2 and "is a folder, not a file" in err and "storage" not in err


def test_events_without_a_robot_include_the_service_wide_ones(
    bench: Bench, capsys: pytest.CaptureFixture[str]
) -> None:
    seen: list[tuple[int, str, str]] = []
    follow = threading.Thread(
        target=lambda: seen.append(
            _cli(capsys, "events", "--json", "-e", bench.endpoint, "--seconds", "2")
        )
    )
    follow.start()
    robot = bench.robot("r5", 2)
    while follow.is_alive():  # until the command ends, whenever it subscribed
        bench.client.put("rlutf/maps/broken", b'{"map_id": "broken", "version": 1}')
        bench.client.put("rlutf/robots/r5/events", b"[[[not an event")  # another tool's
        robot.advance()  # a scan with no initial pose: r5's not_initialized
        time.sleep(0.1)
    follow.join()
    code, out, err = seen[0]
    assert code == 0
    # Said once on stderr (at most a line every 5 s), never mixed into the Events' JSON lines.
    assert err.count("rlutf/robots/r5/events: not an Event (15 bytes") == 1, err
    events = [json.loads(line) for line in out.splitlines()]
    codes = {(e["code"], e["key"]) for e in events}
    assert ("invalid_map", "rlutf/maps/broken") in codes
    assert ("not_initialized", "rlutf/robots/r5/scan") in codes


def test_answers_that_are_no_map_from_another_client_are_said_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Any client may answer gets on the map and map health keys: a reply nested past the
    # parser's depth, or not UTF-8, used to end these commands in "unexpected error".
    with running_bench(tmp_path) as bench:
        bench.put_map()
        time.sleep(0.3)
        bad = {
            "deep": b"[" * 100_000,
            "binary": b"\xff\xfe not json",
            "huge": b'{"map_id": "huge", "version": 1e999}',
        }

        def answer(query: zenoh.Query) -> None:
            for map_id, payload in bad.items():
                for key in (f"rlutf/maps/{map_id}", f"rlutf/maphealth/{map_id}"):
                    if query.key_expr.intersects(zenoh.KeyExpr(key)):
                        query.reply(key, payload)

        rogue = bench.client.declare_queryable("rlutf/**", answer)
        e = bench.endpoint
        code, out, err = _cli(capsys, "map", "list", "-e", e, "--timeout", "2")
        assert code == 0 and "m1" in out and "unexpected error" not in err, err
        for map_id in bad:
            written = tmp_path / f"{map_id}.json"
            for argv in (
                ["map", "get", map_id],
                ["map", "get", map_id, "--out", str(written)],
                ["map", "show", map_id, "--out", str(tmp_path / f"{map_id}.png")],
                ["map", "health", map_id],
            ):
                code, out, err = _cli(capsys, *argv, "-e", e, "--timeout", "2")
                assert "unexpected error" not in err and "Traceback" not in err, (argv, err)
                assert code == 1 and map_id in err, (argv, out, err)
            assert not written.exists()  # nothing that is no map is written
        rogue.undeclare()
