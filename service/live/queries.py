"""Client tools over Zenoh for a running fleet: query poses and instances' health, relocalize."""

from __future__ import annotations

import queue
import sys

import zenoh

from schemas import (
    Event,
    EventCode,
    Health,
    PoseEstimate,
    Relocalize,
    SchemaError,
    decode,
    encode,
    valid_id,
)
from service.keys import Keys


def query_poses(session: zenoh.Session, prefix: str, robot: str, timeout: float) -> int:
    """Print the latest PoseEstimate of one robot (or ``*``: all), one JSON per line."""
    if robot != "*" and not valid_id(robot):
        print(f"rlutf pose: invalid robot id {robot!r}", file=sys.stderr)
        return 2
    key = Keys(prefix).pose(robot)
    found = 0
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            pose = decode(PoseEstimate, reply.ok.payload.to_bytes())
        except SchemaError as err:
            print(f"rlutf pose: bad reply on {reply.ok.key_expr}: {err}", file=sys.stderr)
            continue
        print(encode(pose).decode())
        found += 1
    if not found:
        print(f"rlutf pose: no pose for {robot!r}", file=sys.stderr)
        return 1
    return 0


def query_health(session: zenoh.Session, prefix: str, instance: str, timeout: float) -> int:
    """Print each live instance's Health; 0 if at least one answered."""
    key = Keys(prefix).health(instance)
    found = 0
    for reply in session.get(key, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            health = decode(Health, reply.ok.payload.to_bytes())
        except SchemaError:
            continue
        print(encode(health).decode())
        found += 1
    if not found:
        print("rlutf health: no instance answered", file=sys.stderr)
        return 1
    return 0


def request_relocalize(
    session: zenoh.Session,
    prefix: str,
    robot: str,
    request: Relocalize,
    wait: float,
) -> int:
    """Put a Relocalize for ``robot``; with ``wait`` > 0, follow its events until it ends.

    Prints each Event about the robot (and, while hypotheses remain, their count) as it comes,
    one JSON per line.

    Returns:
        0 when the request was put (``wait`` = 0) or the robot was relocalized; 1 when the
        service answered ``map_not_found`` or ``invalid_message``, or nothing ended the episode
        within ``wait`` seconds.
    """
    keys = Keys(prefix)
    key = keys.robot(robot, "relocalize")
    if wait <= 0:
        session.put(key, encode(request), encoding=zenoh.Encoding.APPLICATION_JSON)
        print(f"put {key}: {encode(request).decode()}")
        return 0
    ended: queue.Queue[int] = queue.Queue()
    seen: dict[str, str] = {"status": "", "hypotheses": ""}
    # What ends the wait: success, or a failure of this request (the map's or the request's key).
    failures = {
        (EventCode.MAP_NOT_FOUND, keys.map(request.map_id)),
        (EventCode.MAP_NOT_FOUND, key),
        (EventCode.INVALID_MESSAGE, key),
    }

    def on_event(sample: zenoh.Sample) -> None:
        try:
            ev = decode(Event, sample.payload.to_bytes())
        except SchemaError:
            return
        print(encode(ev).decode(), flush=True)
        if ev.code == EventCode.RELOCALIZED:
            ended.put(0)
        elif (ev.code, ev.key) in failures:
            ended.put(1)

    def on_pose(sample: zenoh.Sample) -> None:
        try:
            pose = decode(PoseEstimate, sample.payload.to_bytes())
        except SchemaError:
            return
        seen["status"] = pose.status
        seen["hypotheses"] = f", {len(pose.hypotheses)} hypotheses" if pose.hypotheses else ""

    subs = [
        session.declare_subscriber(keys.robot_events(robot), on_event),
        session.declare_subscriber(keys.pose(robot), on_pose),
    ]
    try:
        session.put(key, encode(request), encoding=zenoh.Encoding.APPLICATION_JSON)
        try:
            return ended.get(timeout=wait)
        except queue.Empty:
            last = seen["status"] or "no pose received"
            print(
                f"rlutf relocalize: {robot} not relocalized within {wait:g} s "
                f"(last status: {last}{seen['hypotheses']})",
                file=sys.stderr,
            )
            return 1
    finally:
        for s in subs:
            s.undeclare()
