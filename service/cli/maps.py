"""``rlutf map put|get|list|remove|import|build|show|health``: maps into and out of the store,
from grids and logs, and where the fleet's scans disagree with them."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from service.cli import maphealth
from service.cli.errors import CliError
from service.cli.flags import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    client,
    number,
    seconds,
    timeout_flag,
    writable,
    zenoh_flags,
)
from service.cli.mapmake import cmd_build, cmd_import, why
from service.infile import read_regular
from service.maps.book import FILE_MAX_BYTES


def register(sub: Any) -> None:
    """Add ``map`` and its actions to the ``rlutf`` subcommands."""
    maps = sub.add_parser("map", help="put, get, list, remove, import, build and show maps")
    msub = maps.add_subparsers(dest="map_command", metavar="ACTION")
    maps.set_defaults(func=cmd_map)
    put = msub.add_parser("put", help="store a map (JSON Map message or GeoJSON geometry)")
    put.add_argument("file", type=Path, help="a Map message (JSON) or GeoJSON file")
    put.add_argument(
        "--id",
        dest="map_id",
        type=_map_id,
        help="map id, 1 to 64 of A-Z a-z 0-9 _ - (default: the file's map_id or stem)",
    )
    put.add_argument(
        "--version",
        type=_version,
        default="next",
        metavar="N|next",
        help="version to put: N, or next (the default): the version the store holds plus one, "
        "1 when it holds none; a map equal to the one held is not put again",
    )
    put.add_argument(
        "--timeout",
        type=seconds(minimum=0),
        default=5.0,
        metavar="SECONDS",
        help="seconds to wait for the store's answer (default 5; 0: put it without waiting, "
        "so unconfirmed, with --version N)",
    )
    zenoh_flags(put, client=True)
    get = msub.add_parser("get", help="print a stored map")
    get.add_argument("map_id", help="the map's id")
    get.add_argument("--out", type=Path, help="write to a file instead of stdout")
    timeout_flag(get, what="the storage's answer")
    zenoh_flags(get, client=True)

    ls = msub.add_parser(
        "list",
        help="list the stored maps: id, version, size, and the robots on each",
        description="Ask every storage of {prefix}/maps/* and the live instances: one line per "
        "map with its version, payload size, extent (width x height of its bounding box) and "
        "the robots on it (localized on it, or placed on it and waiting for their first "
        "pose). Exit 1 if no storage answers.",
    )
    timeout_flag(ls, what="the storages' answers")
    ls.add_argument("--json", action="store_true", help="print one JSON array instead of text")
    zenoh_flags(ls, client=True)

    rm = msub.add_parser(
        "remove",
        help="delete a stored map",
        description="Delete {prefix}/maps/ID from the storages (a Zenoh delete on the key) and "
        "check that none answers for it any more. Robots on the map keep the copy their "
        "service holds until it restarts; a new initial pose on it gets map_not_found. A map "
        "that robots are on (with a pose, or placed on it with none yet) is removed only with "
        "--force.",
    )
    rm.add_argument("map_id", metavar="ID", help="the map's id")
    rm.add_argument("--force", action="store_true", help="remove it even if robots are on it")
    timeout_flag(rm, what="the storages to drop the map")
    zenoh_flags(rm, client=True)

    imp = msub.add_parser(
        "import",
        help="import a ROS map_server occupancy grid (YAML + PGM/PNG)",
        description="Turn a ROS map_server grid (slam_toolbox, Cartographer, GMapping) into a "
        "polygon Map: free space as polygons, obstacles as holes, unknown cells as walls.",
    )
    imp.add_argument("yaml", type=Path, help="the map's YAML file")
    _map_output_flags(imp)
    imp.set_defaults(func=cmd_import)

    build = msub.add_parser(
        "build",
        help="build a map from a log of scans with known poses",
        description="Build an occupancy grid from scans with known poses (a CARMEN log with "
        "corrected poses, .log or .log.gz, or an MCAP log in the WIRE.md layout with poses) "
        "and import it like `map import`.",
    )
    build.add_argument(
        "log",
        type=Path,
        nargs="+",
        metavar="LOG",
        help="CARMEN log (.log, .gz), MCAP logs recorded at one time (.mcap files, or a "
        "folder of them: the files every process of one rlutf serve rotated) or, with --ros2, "
        "a bag",
    )
    build.add_argument(
        "--from-map",
        metavar="ID",
        help="with MCAP logs: only the scans of robots localized on map ID (needed when the "
        "logs hold poses on several maps)",
    )
    build.add_argument(
        "--ros2", action="store_true", help="LOG is a rosbag2 recording with scans and poses"
    )
    build.add_argument(
        "--scan-topic", default="/scan", help="with --ros2: LaserScan topic (default /scan)"
    )
    build.add_argument(
        "--pose-topic",
        default="/amcl_pose",
        help="with --ros2: PoseWithCovarianceStamped topic of the poses (default /amcl_pose)",
    )
    build.add_argument(
        "--base-frame",
        default="base_footprint",
        help="with --ros2: the frame the poses are of; each scan is put at its laser from the "
        "bag's tf_static (default base_footprint)",
    )
    build.add_argument(
        "--resolution",
        type=number(above=0),
        default=0.05,
        metavar="M",
        help="cell size, m (default 0.05)",
    )
    build.add_argument(
        "--max-range",
        type=number(above=0),
        default=None,
        metavar="M",
        help="longer ranges are no return, m (default: each scan's range_max; 50 for a CARMEN "
        "log, which has none)",
    )
    build.add_argument(
        "--surface-offset",
        type=number(minimum=0),
        default=None,
        metavar="M",
        help="move the walls this far into the occupied cells, m (default 0.4 cell: a surface "
        "a scanner hit lies inside its cell, half a cell deep on average; 0 traces the cell "
        "edges, as map import does)",
    )
    build.add_argument(
        "--save-grid",
        type=Path,
        metavar="YAML",
        help="also write the grid as map_server YAML + PGM",
    )
    _map_output_flags(build)
    build.set_defaults(func=cmd_build)

    show = msub.add_parser(
        "show",
        help="render a map (file or stored id) to PNG",
        description="Draw a map so a person can check it by eye.",
    )
    show.add_argument("source", help="a map JSON file, or the id of a stored map")
    show.add_argument("--out", type=Path, default=Path("map.png"), help="PNG (default map.png)")
    timeout_flag(show, what="the storage's answer")
    zenoh_flags(show, client=True)
    show.set_defaults(func=cmd_show)
    maphealth.register(msub)


def _map_output_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--id",
        dest="map_id",
        type=_map_id,
        help="map id, 1 to 64 of A-Z a-z 0-9 _ - (default: from the file name)",
    )
    p.add_argument(
        "--version",
        type=_version,
        default=None,
        metavar="N|next",
        help="map version: in the file, 1 unless given; with --put, the version put, by "
        "default next (the store's version plus one)",
    )
    p.add_argument("--out", type=Path, help="write the Map JSON here (default: <id>.json)")
    p.add_argument("--put", action="store_true", help="also put it into the map store")
    p.add_argument(
        "--component",
        type=_component,
        help="free component to keep: index from the report, "
        "a point 'x,y' inside it, or 'all' (default: the largest)",
    )
    p.add_argument(
        "--min-area",
        type=number(minimum=0),
        help="with --component all: drop free islands smaller than this, m^2 (default 1)",
    )
    p.add_argument(
        "--simplify",
        type=number(minimum=0),
        help="simplification tolerance, m (default half a cell; never more than a cell)",
    )
    p.add_argument("--png", type=Path, help="also render the result to this PNG")
    zenoh_flags(p, client=True)


def _version(text: str) -> int | str:
    from service.maps.client import parse_version

    return parse_version(text)


def _map_id(text: str) -> str:
    """``--id``: a map id (an empty or malformed one is refused as the flag's value)."""
    from schemas import valid_id

    if not valid_id(text):
        raise argparse.ArgumentTypeError(f"invalid map id {text!r}: use 1 to 64 of A-Z a-z 0-9 _ -")
    return text


def _component(text: str) -> Any:
    """``--component``: ``all``, an index or a point ``x,y``, read before any work."""
    from service.maps.mapimport import MapImportError, parse_component

    try:
        return parse_component(text)
    except MapImportError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("component: ")) from None


def cmd_map(args: argparse.Namespace) -> int:
    """``rlutf map put|get|list|remove``, and the usage of ``rlutf map`` without an action."""
    from service.maps.client import get_map, put_map

    if args.map_command in ("list", "remove"):
        from service.cli.mapcatalog import cmd_catalog

        return cmd_catalog(args)
    if args.map_command == "put":
        if not args.file.is_file():
            what = (
                "is a folder, not a file"
                if args.file.is_dir()
                else "is not a regular file (a FIFO, a device or a socket)"
                if args.file.exists()
                else "no such file"
            )
            raise CliError(
                f"{args.file}: {what}; give a Map JSON or GeoJSON file (`rlutf map import` "
                "writes one from a map_server grid)",
                EXIT_USAGE,
            )
        if args.timeout == 0 and not isinstance(args.version, int):
            raise CliError(
                "--timeout 0 asks the store nothing, so --version next cannot learn the version "
                "it holds: give --version N with it, or a --timeout above 0",
                EXIT_USAGE,
            )
        settings, session = client(args)
        with session:
            return put_map(
                session, settings.prefix, args.file, args.map_id, args.version, args.timeout
            )
    if args.map_command == "get":
        if args.out is not None:
            writable(args.out, "--out")
        settings, session = client(args)
        with session:
            return get_map(session, settings.prefix, args.map_id, args.out, args.timeout)
    print(
        "rlutf map: choose an action: put, get, list, remove, import, build, show, health "
        "(see rlutf map --help)",
        file=sys.stderr,
    )
    return EXIT_USAGE


def cmd_show(args: argparse.Namespace) -> int:
    """``rlutf map show``."""
    from service.maps.mapimport import MapFileError, MapImportError, render_map

    path = Path(args.source)
    writable(args.out, "--out")
    if path.is_dir():  # a path that exists is read as a file, not asked for as an id
        raise CliError(
            f"{path}: is a folder, not a file; give a map JSON file or the id of a stored map",
            EXIT_USAGE,
        )
    if path.exists():
        try:
            # A BOM is no matter.
            data = json.loads(read_regular(path, FILE_MAX_BYTES).decode("utf-8-sig"))
        except OSError as err:
            raise CliError(f"cannot read {path}: {err.strerror or err}", EXIT_USAGE) from err
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as err:
            where = (
                f" (line {err.lineno}, column {err.colno}: {err.msg})"
                if isinstance(err, json.JSONDecodeError)
                else " (not UTF-8 text)"
                if isinstance(err, UnicodeDecodeError)
                else " (nested deeper than a map can be)"
            )
            from service.maps.client import import_hint

            where += import_hint(path, f"--png {path.stem}.png")
            raise CliError(
                f"{path}: not a map JSON file{where}; give a Map JSON (`rlutf map get` and "
                "`rlutf map import` write one) or the id of a stored map",
                EXIT_USAGE,
            ) from err
        if isinstance(data, dict) and data.get("type") in ("Feature", "FeatureCollection"):
            from service.maps.client import unwrap_geojson

            try:  # GeoJSON as rlutf map put takes it: drawn as the geometry it puts
                data = unwrap_geojson(path, data)["geometry"]
            except ValueError as err:
                print(f"rlutf map show: {err}", file=sys.stderr)
                return EXIT_USAGE
    else:
        from schemas import valid_id
        from service.keys import Keys

        if not valid_id(args.source):
            raise CliError(
                f"{args.source}: no such file, and not a map id (1 to 64 of A-Z a-z 0-9 _ -); "
                "give a map JSON file or the id of a stored map",
                EXIT_USAGE,
            )
        settings, session = client(args)
        with session:
            replies = [
                r.ok
                for r in session.get(Keys(settings.prefix).map(args.source), timeout=args.timeout)
                if r.ok
            ]
        if not replies:
            print(
                f"rlutf map show: {args.source!r} is no file, and no storage answered for a map "
                "of that id (`rlutf map list` shows the stored maps)",
                file=sys.stderr,
            )
            return EXIT_FAILURE
        from schemas import Map, SchemaError, decode

        maps, problem = [], ""
        for reply in replies:  # any client may answer on a map key: the first map is drawn
            payload = reply.payload.to_bytes()
            try:
                decode(Map, payload, max_bytes=len(payload))
                maps.append(payload)
            except SchemaError as err:
                problem = str(err)
        if not maps:
            print(
                f"rlutf map show: the answer for map {args.source!r} is no map: {problem}",
                file=sys.stderr,
            )
            return EXIT_FAILURE
        data = json.loads(maps[0])
    try:
        title = f"{data.get('map_id', path.stem)} v{data.get('version', '?')}"
        render_map(data, args.out, title=title)
    except MapFileError as err:  # the checks passed, the file system refused (/proc, full)
        raise CliError(
            f"--out {args.out}: cannot write the file ({why(err)}); choose another"
        ) from err
    except (MapImportError, ValueError, KeyError, TypeError) as err:
        print(f"rlutf map show: not a map: {err}", file=sys.stderr)
        return EXIT_USAGE if path.exists() else EXIT_FAILURE  # a file given, or a stored map
    print(f"wrote {args.out}")
    return EXIT_OK
