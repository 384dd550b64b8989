"""Instance names: two live instances of one name would each own the same robots.

Seen by a reviewer: a second ``rlutf serve --instance b`` beside a running one started, and
from then on every pose of b's robots was published twice (each took the other's token for its
own), ``rlutf health`` and ``rlutf robots`` merged the two under one name.
"""

from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh
from scaleout_harness import Router, live_members, router_config, spawn_instance, wait_until

from service.cluster.membership import Membership, NameTaken
from service.keys import Keys
from service.live.sessions import free_port, session_config


def test_a_name_whose_token_is_live_is_refused_and_one_that_goes_is_taken() -> None:
    """``claim`` refuses a name with a live token after its wait, and takes one whose token
    goes within it (a restarted instance whose previous run is still leaving)."""
    port = free_port()
    keys = Keys()
    with zenoh.open(router_config(port)) as router:
        client = zenoh.open(session_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
        try:
            token = router.liveliness().declare_token(keys.service("b"))
            time.sleep(0.3)
            begun = time.monotonic()
            with pytest.raises(NameTaken, match="needs a name of its own"):
                Membership("b").claim(client, keys, timeout=1.0, wait=0.5)
            assert time.monotonic() - begun >= 0.5
            Membership("c").claim(client, keys, timeout=1.0, wait=0.5)  # another name: free

            def leave() -> None:
                time.sleep(0.5)
                token.undeclare()

            threading.Thread(target=leave).start()
            Membership("b").claim(client, keys, timeout=1.0, wait=5.0)  # no raise: it went
        finally:
            client.close()


@pytest.mark.integration
def test_a_second_instance_of_a_live_name_refuses_to_start(tmp_path: Path) -> None:
    """A second ``rlutf serve --instance i1`` exits 1 saying why, records nothing, and the
    first keeps its name and its robots."""
    router = Router.open(free_port(), tmp_path / "store")
    (tmp_path / "first").mkdir()
    (tmp_path / "second").mkdir()
    first = spawn_instance(router.endpoint, "i1", tmp_path / "first")
    second = None
    try:
        assert wait_until(lambda: live_members(router.session) == {"i1"}, 25.0), (
            first.log.read_text()[-2000:]
        )
        second = spawn_instance(router.endpoint, "i1", tmp_path / "second")
        try:
            code: int | None = second.process.wait(45.0)
        except subprocess.TimeoutExpired:
            code = None  # still running: it took the name too
        text = second.log.read_text()
        assert code == 1, text[-2000:]
        assert "each instance needs a name of its own" in text, text[-2000:]
        assert not list((tmp_path / "second" / "rec-i1").glob("*.mcap*"))
        assert first.process.poll() is None
        assert live_members(router.session) == {"i1"}
    finally:
        if second is not None:
            second.stop()
        first.stop()
        router.close()
