"""A flood of claim tokens on an instance's name costs bounded memory and log lines.

Found by a reviewer attacking a running ``rlutf serve --instance svc`` from a Zenoh client:
20,000 liveliness tokens ``rlutf/service/svc/claim/{later}/{session}`` (younger claims, which
cannot take the name) cost the service 20,000 WARNING lines and a set entry each, kept after
the tokens went (RSS +38 MB), for ever. Now at most :data:`names.TOLD_MAX` younger claims are
remembered and logged while live, the rest counted; a claim whose token goes is forgotten.
Real Zenoh sessions on loopback.
"""

from __future__ import annotations

import logging
import time

import pytest
import zenoh
from scaleout_harness import router_config

from service.cluster import names
from service.cluster.names import Claim, NameClaim, claim_key
from service.keys import Keys
from service.live.sessions import free_port, session_config

KEYS = Keys()
FLOOD = 400


def test_a_flood_of_younger_claims_is_remembered_and_logged_a_bounded_number_of_times(
    caplog: pytest.LogCaptureFixture,
) -> None:
    port = free_port()
    with zenoh.open(router_config(port)) as router:
        client = zenoh.open(session_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
        told: list[str] = []
        mine = NameClaim("b", KEYS, told.append)
        try:
            mine.take(client, timeout=1.0)
            assert mine.own is not None
            caplog.set_level(logging.WARNING, logger="service.cluster.names")
            caplog.clear()
            base = mine.own.claimed_ns + 1_000_000
            tokens = [
                router.liveliness().declare_token(claim_key(KEYS, "b", Claim(base + i, f"x{i}")))
                for i in range(FLOOD)
            ]
            deadline = time.monotonic() + 20.0
            while time.monotonic() < deadline:
                with mine._lock:
                    seen = len(mine._told) + mine.unlisted
                if seen >= FLOOD:
                    break
                time.sleep(0.05)
            assert seen == FLOOD
            assert len(mine._told) <= names.TOLD_MAX
            assert mine.unlisted == FLOOD - len(mine._told)
            assert mine.figures()["younger_claims_unlisted"] == mine.unlisted
            lines = [r for r in caplog.records if "claimed the name after" in r.getMessage()]
            assert len(lines) <= names.TOLD_MAX
            assert told == [] and mine.lost is None
            for token in tokens:
                token.undeclare()
            deadline = time.monotonic() + 10.0
            while mine._told and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not mine._told  # the tokens went: nothing of them is kept
            # an older claim still stops this instance, flood or not
            older = Claim(mine.own.claimed_ns - 1, "00")
            router.liveliness().declare_token(claim_key(KEYS, "b", older))
            deadline = time.monotonic() + 5.0
            while not told and time.monotonic() < deadline:
                time.sleep(0.05)
            assert len(told) == 1 and mine.lost == told[0]
        finally:
            mine.close()
            client.close()
