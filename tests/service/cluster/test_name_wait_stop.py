"""An instance that waits for its name's tokens to go (a previous run of it still on the bus)
says so, and stops at once when told to (SIGTERM), exit 0.

Before, the wait was silent and deaf: SIGTERM was heard only when the wait ended, up to 12 s
later (past ``docker stop``'s 10 s grace), and the service then said the name was taken and
exited 1. A real router, a real member token of the name, a real ``rlutf serve``.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from scaleout_harness import Router, spawn_instance, wait_until

from service.keys import Keys
from service.live.sessions import free_port

pytestmark = pytest.mark.integration


def test_sigterm_while_waiting_for_the_name_stops_at_once(tmp_path: Path) -> None:
    router = Router.open(free_port(), tmp_path / "store")
    # a previous run of i1, frozen: its member token is still on the bus
    token = router.session.liveliness().declare_token(Keys().service("i1"))
    instance = spawn_instance(router.endpoint, "i1", tmp_path)
    try:
        assert wait_until(lambda: "waiting up to" in instance.log.read_text(), 60.0), (
            instance.log.read_text()[-2000:]
        )
        t0 = time.monotonic()
        instance.process.send_signal(signal.SIGTERM)
        code = instance.process.wait(30.0)
        took = time.monotonic() - t0
        text = instance.log.read_text()
        assert code == 0, text[-2000:]
        assert took < 3.0, (took, text[-2000:])
        assert "each instance needs a name of its own" not in text
    finally:
        instance.stop()
        token.undeclare()
        router.close()
