"""ROS 2 bags for ``rlutf replay --ros2`` and ``rlutf map build --ros2``.

``rlutf replay BAG --ros2 --map ID_OR_FILE --initial-pose X,Y,THETA --out OUT.mcap`` turns the
bag into a replay input (:func:`service.ros2.bags.bag_inputs`, written next to OUT and removed
after), replays it like any log, and with ``--ros2-out BAG`` writes the poses as a rosbag2 MCAP.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def replay_flags(p: argparse.ArgumentParser) -> None:
    """The flags of ``rlutf replay --ros2``."""
    g = p.add_argument_group("ROS 2 bags (--ros2)")
    g.add_argument(
        "--ros2", action="store_true", help="IN is a rosbag2 recording (folder or .mcap)"
    )
    g.add_argument(
        "--map", dest="ros_map", metavar="ID_OR_FILE", help="map id (in --store) or file"
    )
    g.add_argument("--store", type=Path, default=Path("store"), help="map store (default: store)")
    g.add_argument(
        "--initial-pose", metavar="X,Y,THETA", help="robot pose in the map at the first scan"
    )
    g.add_argument("--scan-topic", default="/scan", help="LaserScan topic (default /scan)")
    g.add_argument("--odom-topic", default="/odom", help="Odometry topic (default /odom)")
    g.add_argument("--odom-tf", action="store_true", help="odometry from odom -> base on tf")
    g.add_argument(
        "--base-frame", default="base_footprint", help="base frame (default base_footprint)"
    )
    g.add_argument(
        "--odom-frame",
        default="odom",
        help="odometry frame: read with --odom-tf, written as map -> it (default odom)",
    )
    g.add_argument("--robot", help="robot id (default: the scan topic's namespace, else 'robot')")
    g.add_argument(
        "--ros2-out", type=Path, metavar="BAG", help="also write the poses as a rosbag2 MCAP"
    )


#: The flags of ``rlutf replay`` that only a bag (``--ros2``) reads, and their defaults.
BAG_ONLY = {
    "ros_map": ("--map", None),
    "store": ("--store", Path("store")),
    "initial_pose": ("--initial-pose", None),
    "scan_topic": ("--scan-topic", "/scan"),
    "odom_topic": ("--odom-topic", "/odom"),
    "odom_tf": ("--odom-tf", False),
    "base_frame": ("--base-frame", "base_footprint"),
    "odom_frame": ("--odom-frame", "odom"),
    "robot": ("--robot", None),
    "ros2_out": ("--ros2-out", None),
}


def check_flags(args: argparse.Namespace) -> None:
    """Refuse, before any work, the bag flags given without ``--ros2`` (they were ignored in
    silence: ``--ros2-out`` wrote nothing, exit 0) and a ``--ros2-out`` that exists (it was
    refused once the replay was done) or whose folder does not (it was made, where ``--out``
    refuses).

    Raises:
        CliError: naming the flags and the fix (exit 2).
    """
    from schemas import valid_id
    from service.cli.errors import CliError
    from service.cli.flags import EXIT_USAGE, writable
    from service.keys import printable

    if not args.ros2:
        given = [flag for key, (flag, default) in BAG_ONLY.items() if getattr(args, key) != default]
        if given:
            raise CliError(
                f"{', '.join(given)}: only read with --ros2 (IN a rosbag2 recording); give "
                "--ros2, or leave them out to replay rlutf logs",
                EXIT_USAGE,
            )
    elif args.robot is not None and not valid_id(args.robot):
        raise CliError(
            f"--robot {printable(args.robot)!r}: not a robot id: use 1 to 64 of A-Z a-z 0-9 _ -",
            EXIT_USAGE,
        )
    elif args.ros2_out is not None and (args.ros2_out.exists() or args.ros2_out.is_symlink()):
        raise CliError(
            f"--ros2-out {args.ros2_out}: exists already (a rosbag2 is written as a new "
            "folder); remove it or choose another",
            EXIT_USAGE,
        )
    elif args.ros2_out is not None:  # its folder must exist, as --out's (it was made)
        writable(args.ros2_out, "--ros2-out")


def load_map(spec: str, store: Path) -> bytes:
    """A Map payload from a file (Map JSON, GeoJSON or map_server YAML) or a stored map id.

    Raises:
        ValueError: no such file or stored map, or an invalid one.
    """
    from schemas import Map, SchemaError, decode, encode, valid_id
    from service.maps.book import FILE_MAX_BYTES
    from service.maps.client import map_message_from_file

    path = Path(spec)
    if path.is_file():
        if path.suffix.lower() in (".yaml", ".yml"):
            from service.maps.mapimport import MapImportError, import_grid

            try:
                data = import_grid(path).map
                return encode(decode(Map, json.dumps(data), max_bytes=FILE_MAX_BYTES))
            except (MapImportError, SchemaError) as err:
                raise ValueError(f"{path}: {err}") from err
        return map_message_from_file(path, None, None)
    if not valid_id(spec):
        raise ValueError(f"--map {spec!r}: neither a file nor a map id")
    from service.maps.files import FileMapStore

    payload = FileMapStore(store).get(spec)
    if payload is None:
        raise ValueError(f"--map {spec!r}: no such map in {store} (give a file instead)")
    return payload


def _initial(text: str | None) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        x, y, theta = (float(v) for v in text.split(","))
    except ValueError as err:
        raise ValueError(f"--initial-pose {text!r}: expected X,Y,THETA") from err
    return x, y, theta


def topics(args: argparse.Namespace) -> Any:
    """The BagTopics of the flags."""
    from service.ros2.bags import BagTopics

    return BagTopics(
        scan=args.scan_topic,
        odom=args.odom_topic,
        odom_tf=args.odom_tf,
        odom_frame=args.odom_frame,
        base_frame=args.base_frame,
    )


def bag_to_log(args: argparse.Namespace, bag: Path, log_path: Path) -> Any:
    """Convert ``bag`` into the replay input ``log_path``; returns the BagSummary.

    Raises:
        ValueError: a bad flag, map or bag (the message says which).
    """
    from service.config import Settings
    from service.ros2.bags import BagError, bag_inputs

    if not args.ros_map:
        raise ValueError("--ros2 needs --map ID_OR_FILE")
    payload = load_map(args.ros_map, args.store)
    config = Settings(listen=[], instance="replay").effective()
    try:
        with open(log_path, "wb") as f:
            return bag_inputs(
                bag,
                f,
                payload,
                topics(args),
                initial=_initial(args.initial_pose),
                robot_id=args.robot,
                config=config,
            )
    except BagError as err:
        raise ValueError(str(err)) from err


def write_out(args: argparse.Namespace, result: Any, summary: Any) -> tuple[int, int]:
    """Write the replay's poses to ``--ros2-out``; returns the numbers of ``amcl_pose`` and
    ``tf`` messages."""
    from service.ros2.bags import write_pose_bag

    poses = {robot: [p.payload for p in recs] for robot, recs in result.recomputed.items()}
    return write_pose_bag(
        args.ros2_out,
        poses,
        result.odometry,
        {summary.robot: summary.namespace},
        odom_frame=args.odom_frame,
    )
