"""The input loop (service.live.loop) over real Zenoh sessions on loopback: once it has caught
up it waits, and what comes meanwhile is taken in together, in one round."""

from __future__ import annotations

import time

import zenoh

from service.live.loop import InputLoop
from service.live.sessions import client_config, free_port, session_config


class _Counted(InputLoop):
    """The loop, with the samples each of its rounds took in."""

    rounds: list[int]

    def _take(self) -> int:
        taken = super()._take()
        if taken:
            self.rounds.append(taken)
        return taken


def _burst(wait_s: float, count: int, settle_s: float = 10.0) -> tuple[list[int], list[str], float]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(session_config("router", listen=[endpoint]))
    robot = zenoh.open(client_config(endpoint))
    got: list[str] = []
    loop = _Counted(lambda sample: got.append(str(sample.key_expr)), None, wait_s=wait_s)
    loop.rounds = []
    try:
        loop.start(router, "rlutf/robots/*/*")
        time.sleep(0.5)  # the subscription reaches the client; the loop is waiting
        for i in range(count):
            robot.put(f"rlutf/robots/r{i:02d}/odom", b"{}")
        deadline = time.monotonic() + settle_s
        while len(got) < count and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        started = time.monotonic()
        loop.close()
        closed_in = time.monotonic() - started
        robot.close()
        router.close()
    return loop.rounds, got, closed_in


def test_inputs_that_come_while_the_loop_waits_are_taken_in_one_round() -> None:
    rounds, got, _ = _burst(wait_s=1.0, count=20)
    assert sorted(got) == [f"rlutf/robots/r{i:02d}/odom" for i in range(20)]
    # Put within a millisecond, during a wait of a second: one round took them all.
    assert rounds == [20]


def test_a_waiting_loop_stops_at_once() -> None:
    # an input comes during the wait; the loop is closed before the wait would have ended
    _, _, closed_in = _burst(wait_s=30.0, count=1, settle_s=0.2)
    assert closed_in < 5.0  # not the 30 s wait
