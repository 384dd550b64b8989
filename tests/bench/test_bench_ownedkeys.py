"""bench.ownedkeys's patch of the benchmark's service, over real Zenoh sessions on loopback: an
input loop subscribed to its own robots' keys and every pose, and no KeyWatch."""

from __future__ import annotations

import time
from typing import Any

import pytest
import zenoh

from bench import ownedkeys
from service.cluster.membership import owner_of
from service.live.keywatch import KeyWatch
from service.live.loop import InputLoop
from service.live.node import LocalizationService
from service.live.sessions import free_port

NAMES = ["fleetbench-p0", "fleetbench-p1"]
ROBOTS = [f"r{i:03d}" for i in range(8)]


def _session(mode: str, endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", f'"{mode}"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    where = "listen/endpoints" if mode == "router" else "connect/endpoints"
    conf.insert_json5(where, f'["{endpoint}"]')
    return zenoh.open(conf)


@pytest.fixture
def patched(monkeypatch: pytest.MonkeyPatch) -> None:
    for cls in (KeyWatch, InputLoop, LocalizationService):
        monkeypatch.setattr(cls, "start", cls.start)  # put back after the test
    monkeypatch.setenv(ownedkeys.ENV, f"{','.join(NAMES)};{','.join(ROBOTS)}")
    monkeypatch.setitem(ownedkeys.PROCESS, "name", NAMES[1])
    ownedkeys.install()


@pytest.mark.usefixtures("patched")
def test_the_patched_loop_takes_its_own_robots_inputs_and_every_pose() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = _session("router", endpoint)
    robots = _session("client", endpoint)
    got: list[str] = []
    loop = InputLoop(lambda sample: got.append(str(sample.key_expr)), None)
    try:
        loop.start(router, "rlutf/robots/*/*")
        time.sleep(0.5)  # the subscriptions reach the client
        for r in ROBOTS:
            for leaf in ("odom", "scan", "pose"):
                robots.put(f"rlutf/robots/{r}/{leaf}", b"{}")
        mine = [r for r in ROBOTS if owner_of(r, NAMES) == NAMES[1]]
        # Its own robots' channels take every leaf: a pose of one of them put by another
        # session comes on both (the service's own poses never come back to it).
        want = [f"rlutf/robots/{r}/{leaf}" for r in mine for leaf in ("odom", "scan", "pose")]
        want += [f"rlutf/robots/{r}/pose" for r in ROBOTS]
        deadline = time.monotonic() + 10
        while len(got) < len(want) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.2)  # anything more would come now
    finally:
        loop.close()
        robots.close()
        router.close()
    assert 0 < len(mine) < len(ROBOTS)  # the split is a real one
    assert sorted(got) == sorted(want)  # no wildcard on the other robots' inputs


@pytest.mark.usefixtures("patched")
def test_the_patched_keywatch_subscribes_to_nothing() -> None:
    watch: Any = KeyWatch.__new__(KeyWatch)
    watch._subscriber = None
    KeyWatch.start(watch, None, None)  # type: ignore[arg-type]  # no session is touched
    assert watch._subscriber is None


def test_without_the_variable_nothing_is_patched(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ownedkeys.ENV, raising=False)
    before = (KeyWatch.start, InputLoop.start, LocalizationService.start)
    ownedkeys.install()
    assert (KeyWatch.start, InputLoop.start, LocalizationService.start) == before
