"""Flag groups and exit codes shared by the command groups, and the client session they open.

Zenoh flags are named like zenoh's own tools (``--mode``, ``--listen``, ``--connect``,
``--config``); the service's settings flags feed :func:`service.config.load_settings`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


def zenoh_flags(p: argparse.ArgumentParser, *, client: bool) -> None:
    """Add the zenoh flags and ``--prefix``; ``client``: a tool that joins a running fleet."""
    g = p.add_argument_group("zenoh (named like zenoh's own tools)")
    g.add_argument(
        "-m",
        "--mode",
        choices=["router", "peer", "client"],
        help="zenoh mode" + (" (default: client)" if client else " (default: router)"),
    )
    if not client:
        g.add_argument(
            "-l",
            "--listen",
            action="append",
            metavar="ENDPOINT",
            help="endpoint to listen on, repeatable (default: tcp/[::]:7447)",
        )
    g.add_argument(
        "-e",
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to connect to, repeatable"
        + (" (default: tcp/127.0.0.1:7447)" if client else ""),
    )
    g.add_argument("-c", "--config", type=Path, metavar="FILE", help="zenoh JSON5 config file")
    p.add_argument("--prefix", help="key prefix (default: rlutf)")


def settings_flags(p: argparse.ArgumentParser) -> None:
    """Add the flags of the service's settings (``serve`` and ``config``)."""
    p.add_argument(
        "--settings",
        type=Path,
        metavar="FILE",
        help="settings file (JSON, TOML or YAML); also RLUTF_SETTINGS",
    )
    p.add_argument("--instance", help="instance name (default: host-pid)")
    p.add_argument("--store", type=Path, metavar="DIR", help="map store folder (default: store)")
    p.add_argument(
        "--no-store",
        action="store_true",
        default=None,
        help="do not host the map storage (use zenohd's storage manager)",
    )
    p.add_argument(
        "--state", type=Path, metavar="DIR", help="pose state folder (default: STORE/state)"
    )
    p.add_argument(
        "--no-state", action="store_true", default=None, help="keep no pose state across restarts"
    )
    p.add_argument("--record", type=Path, metavar="DIR", help="MCAP log folder (default: logs)")
    p.add_argument("--no-record", action="store_true", default=None, help="do not record")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes (-1: one per core, the default; 0: in-process thread)",
    )
    p.add_argument(
        "--metrics-port",
        type=int,
        metavar="PORT",
        help="serve Prometheus metrics on http://ADDR:PORT/metrics (default: off); "
        "also RLUTF_METRICS_PORT",
    )
    p.add_argument(
        "--metrics-addr", metavar="ADDR", help="address of the metrics endpoint (default 0.0.0.0)"
    )
    p.add_argument(
        "--foxglove-port",
        type=int,
        metavar="PORT",
        help="serve a live view on ws://ADDR:PORT for the Foxglove app (Open connection, "
        "Foxglove WebSocket; default: off; 0: any free port); also RLUTF_FOXGLOVE_PORT",
    )
    p.add_argument(
        "--foxglove-addr",
        metavar="ADDR",
        help="address of the live view (default 127.0.0.1; 0.0.0.0 for other hosts)",
    )


def ros2_flags(p: argparse.ArgumentParser) -> None:
    """Add the flags of the ROS 2 front door (``ros2.*`` settings)."""
    g = p.add_argument_group("ROS 2 robots (rmw_zenoh)")
    g.add_argument(
        "--ros2", action="store_true", default=None, help="serve ROS 2 robots on rmw_zenoh's keys"
    )
    g.add_argument(
        "--ros-domain-id",
        type=int,
        metavar="N",
        help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)",
    )
    g.add_argument("--ros-map", metavar="ID", help="the map ROS robots are localized on")
    g.add_argument(
        "--ros-odom",
        choices=["odom", "tf"],
        help="odometry from nav_msgs/Odometry on odom (default) or odom -> base on tf",
    )
    g.add_argument("--ros-base-frame", metavar="FRAME", help="base frame (default base_footprint)")
    g.add_argument("--ros-pose-topic", metavar="TOPIC", help="output topic (default amcl_pose)")
    g.add_argument(
        "--ros-map-topic", metavar="TOPIC", help="import maps from an OccupancyGrid topic"
    )


def _ros2_overrides(args: argparse.Namespace) -> dict[str, Any] | None:
    given = {
        "enabled": getattr(args, "ros2", None),
        "domain_id": getattr(args, "ros_domain_id", None),
        "map_id": getattr(args, "ros_map", None),
        "odom_source": getattr(args, "ros_odom", None),
        "base_frame": getattr(args, "ros_base_frame", None),
        "pose_topic": getattr(args, "ros_pose_topic", None),
        "map_topic": getattr(args, "ros_map_topic", None),
    }
    given = {k: v for k, v in given.items() if v is not None}
    return given or None


def load(args: argparse.Namespace) -> Any:
    """The effective settings of :func:`zenoh_flags` and :func:`settings_flags`.

    Raises:
        SystemExit: the configuration is invalid or the settings file cannot be read.
    """
    from pydantic import ValidationError

    from service.config import load_settings

    try:
        return load_settings(
            args.settings,
            mode=args.mode,
            listen=args.listen,
            connect=args.connect,
            zenoh_config=args.config,
            prefix=args.prefix,
            instance=args.instance,
            store_dir=args.store,
            no_store=args.no_store,
            state_dir=args.state,
            no_state=args.no_state,
            record_dir=args.record,
            no_record=args.no_record,
            workers=args.workers,
            metrics_port=args.metrics_port,
            metrics_addr=args.metrics_addr,
            foxglove_port=getattr(args, "foxglove_port", None),
            foxglove_addr=getattr(args, "foxglove_addr", None),
            ros2=_ros2_overrides(args),
        )
    except ValidationError as err:
        raise SystemExit(f"rlutf: invalid configuration:\n{err}") from err
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"rlutf: {err}") from err


def client(args: argparse.Namespace) -> Any:
    """The settings and an open client session of a tool's :func:`zenoh_flags` (``client``).

    Raises:
        SystemExit: no zenoh router is reachable.
    """
    import zenoh

    from service.config import Settings

    settings = Settings(
        mode=args.mode or "client",
        connect=args.connect or ["tcp/127.0.0.1:7447"],
        listen=[],
        zenoh_config=args.config,
        **({"prefix": args.prefix} if args.prefix else {}),
    )
    from service.live.sessions import zenoh_config

    try:
        return settings, zenoh.open(zenoh_config(settings))
    except zenoh.ZError as err:
        raise SystemExit(
            f"rlutf: cannot reach zenoh at {', '.join(settings.connect)}: {err}"
        ) from err
