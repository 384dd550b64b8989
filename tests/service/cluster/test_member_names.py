"""Only a liveliness token whose name could be an instance's makes a member.

Found by a reviewer declaring tokens on a running ``rlutf serve``: a token on the key expression
``rlutf/service/*`` (a wildcard, which no instance can be named) joined the members as ``*``, and
rendezvous hashing gave it its share of the robots, which nobody then localized. Real Zenoh
sessions on loopback.
"""

from __future__ import annotations

import time

import zenoh
from scaleout_harness import router_config, wait_until

from service.cluster.membership import Membership
from service.keys import Keys
from service.live.sessions import free_port, session_config

KEYS = Keys()


def test_wildcard_and_malformed_tokens_are_no_members() -> None:
    port = free_port()
    with zenoh.open(router_config(port)) as router:
        client = zenoh.open(session_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
        mine = Membership("a")
        try:
            fakes = [
                client.liveliness().declare_token(key)
                for key in ("rlutf/service/*", "rlutf/service/a$*b", "rlutf/service/" + "x" * 65)
            ]
            real = client.liveliness().declare_token("rlutf/service/b")
            time.sleep(0.3)
            mine.start(router, KEYS, timeout=1.0)
            assert wait_until(lambda: mine.members == ["a", "b"], 3.0), mine.members
            later = client.liveliness().declare_token("rlutf/service/**")
            time.sleep(0.5)
            assert mine.members == ["a", "b"]
            # every robot is this instance's or b's: none is left to a name nobody has
            owners = {mine.owner(f"r{i}") for i in range(200)}
            assert owners == {"a", "b"}
            for token in (*fakes, real, later):
                token.undeclare()
            assert wait_until(lambda: mine.members == ["a"], 3.0), mine.members
        finally:
            mine.close()
            client.close()
