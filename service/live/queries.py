"""Client tools over Zenoh for a running fleet: query poses and instances' health."""

from __future__ import annotations

import sys

import zenoh

from schemas import Health, PoseEstimate, SchemaError, decode, encode, valid_id
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
