"""What a real service answers over a real Zenoh session on ``{prefix}/mapversions/{map_id}``
and ``{prefix}/service/{instance}/robots`` is, byte for byte, what the wire models of
:mod:`schemas` encode (StoredVersion, RobotsAnswer), and decodes as them."""

from __future__ import annotations

import hashlib
import time

import pytest
from service_harness import Bench, drive, wait_until

from schemas import (
    Map,
    PoseEstimate,
    RobotsAnswer,
    RobotState,
    StoredVersion,
    WaitingRobot,
    decode,
    encode,
    encode_answer,
)
from service.live.robots import one_sigma

pytestmark = pytest.mark.integration


def answer_bytes(bench: Bench, key: str) -> bytes:
    """The one reply to a get on ``key``, as it came off the bus."""
    (payload,) = [
        r.ok.payload.to_bytes() for r in bench.client.get(key, timeout=2.0) if r.ok is not None
    ]
    return payload


def test_the_stored_version_is_the_bytes_of_the_model(bench: Bench) -> None:
    # asked by its id, a map the store holds nothing of (the bytes as the store always wrote them)
    nothing = answer_bytes(bench, "rlutf/mapversions/nothing")
    expected = StoredVersion(map_id="nothing", version=None, digest=None)
    assert nothing == encode_answer(expected)
    assert (
        nothing == b'{"map_id":"nothing","version":null,"digest":null,"removed":false,"pending":0}'
    )
    assert decode(StoredVersion, nothing) == expected

    bench.put_map("m1", version=3)
    digest = hashlib.sha256(
        encode(Map(map_id="m1", version=3, geometry=bench.world.to_geojson()))
    ).hexdigest()
    held = StoredVersion(map_id="m1", version=3, digest=digest)
    assert wait_until(lambda: answer_bytes(bench, "rlutf/mapversions/m1") == encode_answer(held))
    assert decode(StoredVersion, answer_bytes(bench, "rlutf/mapversions/m1")) == held

    bench.client.delete("rlutf/maps/m1")  # removed: the version stays the one to beat
    removed = StoredVersion(map_id="m1", version=3, digest=digest, removed=True)
    assert wait_until(lambda: answer_bytes(bench, "rlutf/mapversions/m1") == encode_answer(removed))
    payload = answer_bytes(bench, "rlutf/mapversions/m1")
    assert decode(StoredVersion, payload) == removed and removed.held == (3, digest)


def test_the_robots_answer_is_the_bytes_of_the_model(bench: Bench) -> None:
    me = bench.service.settings.instance

    def waiting_both() -> bool:
        answer = decode(RobotsAnswer, answer_bytes(bench, f"rlutf/service/{me}/robots"))
        return [w.robot_id for w in answer.waiting] == ["r7", "r9"]

    last = drive(bench, ["r2", "r1"], 6)
    bench.robot("r7", 4).initial_pose("m1")  # placed, no scan yet: waiting, on its map
    scanning = bench.robot("r9", 3)  # scans with no initial pose: waiting, on no map
    scanning.odom(0)
    for _ in range(50):  # until the service has turned a scan into a not_initialized Event
        scanning.advance()
        if waiting_both():
            break
        time.sleep(0.05)
    else:
        pytest.fail("r7 and r9 never both waited in the robots view")
    payload = answer_bytes(bench, f"rlutf/service/{me}/robots")
    answer = decode(RobotsAnswer, payload)
    assert encode_answer(answer) == payload

    # The same answer built from what a client sees: each robot's latest pose off the bus, and
    # the clock readings only the instance knows (when it answered, the poses' ages).
    got = {s.robot_id: s for s in answer.robots}
    waits = {w.robot_id: w for w in answer.waiting}
    states = []
    for robot_id in ("r1", "r2"):
        pose = PoseEstimate.model_validate(last[robot_id])
        sigma_xy, sigma_theta = one_sigma(pose.covariance)
        states.append(
            RobotState(
                robot_id=robot_id,
                map_id="m1",
                status=pose.status,
                x=pose.x,
                y=pose.y,
                theta=pose.theta,
                age_s=got[robot_id].age_s,
                latency_ms=got[robot_id].latency_ms,
                owner=me,
                localization_score=pose.localization_score,
                deviation_range=pose.deviation_range,
                sigma_xy_m=sigma_xy,
                sigma_theta_rad=sigma_theta,
            )
        )
    expected = RobotsAnswer(
        instance=me,
        stamp_ns=answer.stamp_ns,
        robots=tuple(states),
        waiting=(
            WaitingRobot(
                robot_id="r7", reason="no_scan_yet", age_s=waits["r7"].age_s, owner=me, map_id="m1"
            ),
            WaitingRobot(
                robot_id="r9", reason="not_initialized", age_s=waits["r9"].age_s, owner=me
            ),
        ),
    )
    assert encode_answer(expected) == payload
    assert all(s.age_s is not None and s.latency_ms is not None for s in answer.robots)
    assert b'"map_id":null' in payload  # r9's: optional fields are written as null
