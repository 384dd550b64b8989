"""``rlutf pose|health``: ask a running fleet for poses and instances' health."""

from __future__ import annotations

import argparse
from typing import Any

from service.cli.flags import client, zenoh_flags


def register(sub: Any) -> None:
    """Add ``pose`` and ``health`` to the ``rlutf`` subcommands."""
    pose = sub.add_parser("pose", help="query the latest pose of one robot or all")
    pose.add_argument("robot", nargs="?", default="*", help="robot id (default: all)")
    pose.add_argument("--timeout", type=float, default=3.0)
    zenoh_flags(pose, client=True)
    pose.set_defaults(func=cmd_pose)

    health = sub.add_parser("health", help="query instances' health; exit 1 if none answers")
    health.add_argument("--timeout", type=float, default=3.0)
    health.add_argument("--instance", default="*", help="instance name (default: all)")
    zenoh_flags(health, client=True)
    health.set_defaults(func=cmd_health)


def cmd_pose(args: argparse.Namespace) -> int:
    """``rlutf pose [ROBOT]``."""
    from service.live.queries import query_poses

    settings, session = client(args)
    with session:
        return query_poses(session, settings.prefix, args.robot, args.timeout)


def cmd_health(args: argparse.Namespace) -> int:
    """``rlutf health``: 0 if an instance answers."""
    from service.live.queries import query_health

    settings, session = client(args)
    with session:
        return query_health(session, settings.prefix, args.instance, args.timeout)
