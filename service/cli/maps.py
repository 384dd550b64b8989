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
    timeout_flag,
    writable,
    zenoh_flags,
)


def register(sub: Any) -> None:
    """Add ``map`` and its actions to the ``rlutf`` subcommands."""
    maps = sub.add_parser("map", help="put, get, list, remove, import, build and show maps")
    msub = maps.add_subparsers(dest="map_command", metavar="ACTION")
    maps.set_defaults(func=cmd_map)
    put = msub.add_parser("put", help="store a map (JSON Map message or GeoJSON geometry)")
    put.add_argument("file", type=Path)
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
        type=number(minimum=0),
        default=5.0,
        metavar="SECONDS",
        help="seconds to wait for the store's answer (default 5; 0: put it without waiting, "
        "so unconfirmed, with --version N)",
    )
    zenoh_flags(put, client=True)
    get = msub.add_parser("get", help="print a stored map")
    get.add_argument("map_id")
    get.add_argument("--out", type=Path, help="write to a file instead of stdout")
    timeout_flag(get, what="the storage's answer")
    zenoh_flags(get, client=True)

    ls = msub.add_parser(
        "list",
        help="list the stored maps: id, version, size, and the robots on each",
        description="Ask every storage of {prefix}/maps/* and the live instances: one line per "
        "map with its version, payload size, extent (width x height of its bounding box) and "
        "the robots localized on it. Exit 1 if no storage answers.",
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
        "that robots are on is removed only with --force.",
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
    build.add_argument("--scan-topic", default="/scan", help="with --ros2: LaserScan topic")
    build.add_argument(
        "--pose-topic",
        default="/amcl_pose",
        help="with --ros2: PoseWithCovarianceStamped topic of the poses (default /amcl_pose)",
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
        default=50.0,
        metavar="M",
        help="longer ranges are no return, m (default 50)",
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
            what = "is a folder, not a file" if args.file.is_dir() else "no such file"
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


def _options(args: argparse.Namespace) -> dict[str, Any]:
    opts: dict[str, Any] = {"version": args.version if isinstance(args.version, int) else 1}
    if args.component is not None:
        opts["component"] = args.component
    if args.min_area is not None:
        opts["min_area"] = args.min_area
    if args.simplify is not None:
        opts["simplify"] = args.simplify
    return opts


def _finish(args: argparse.Namespace, result: Any) -> int:
    from service.maps.mapimport import MapFileError, render_map

    print("\n".join(result.report))
    mid = result.map["map_id"]
    out = args.out or Path(f"{mid}.json")
    try:
        out.write_text(json.dumps(result.map), encoding="utf-8")
    except OSError as err:  # the checks passed, the file system refused (/proc, full)
        flag = "--out " if args.out else ""
        raise CliError(
            f"{flag}{out}: cannot write the file ({err.strerror or err}); choose another"
        ) from err
    print(f"wrote {out}")
    if args.png:
        try:
            render_map(result.map, args.png, title=f"{mid} v{result.map['version']}")
        except MapFileError as err:
            raise CliError(
                f"--png {args.png}: cannot write the file ({_why(err)}); choose another"
            ) from err
        print(f"wrote {args.png}")
    if args.put:
        from service.maps.client import put_map

        settings, session = client(args)
        with session:
            version = args.version if args.version is not None else "next"
            return put_map(session, settings.prefix, out, mid, version)
    return EXIT_OK


def _outputs(args: argparse.Namespace) -> None:
    """Refuse output paths that cannot be written before the work starts."""
    for flag in ("out", "png", "save_grid"):
        path = getattr(args, flag, None)
        if path is not None:
            writable(path, "--" + flag.replace("_", "-"))


def _inputs(paths: list[Path], what: str, *, folders: bool) -> None:
    """Refuse input paths that do not exist (or are folders, unless ``folders``) before the
    work starts."""
    for path in paths:
        if not path.exists():
            raise CliError(f"{path}: no such file; give {what}", EXIT_USAGE)
        if path.is_dir() and not folders:
            raise CliError(f"{path}: is a folder, not a file; give {what}", EXIT_USAGE)


def cmd_import(args: argparse.Namespace) -> int:
    """``rlutf map import``."""
    from service.maps.mapimport import MapImportError, import_grid

    _inputs(
        [args.yaml], "the map's YAML file (map_server writes it beside the image)", folders=False
    )
    _outputs(args)
    try:
        result = import_grid(args.yaml, map_id=args.map_id, **_options(args))
    except MapImportError as err:
        print(f"rlutf map import: {err}", file=sys.stderr)
        return EXIT_FAILURE
    return _finish(args, result)


def cmd_build(args: argparse.Namespace) -> int:
    """``rlutf map build``."""
    from service.logs.mcapread import LogError
    from service.maps.mapimport import (
        BUILT_SURFACE_CELLS,
        DEFAULT_MIN_AREA,
        MapImportError,
        build_grid,
        grid_to_map,
        map_id_from_name,
        read_carmen,
        save_grid,
    )

    _inputs(
        args.log,
        "a CARMEN log, MCAP logs (files or a folder of them) or, with --ros2, a bag",
        folders=True,
    )
    _outputs(args)
    _cell_flags(args)
    log = args.log[0]
    mcap = not args.ros2 and (log.is_dir() or log.suffix == ".mcap")
    if mcap:
        from service.logs.mcapread import NotALog
        from service.logs.runs import log_files

        try:  # a folder with no log in it is refused before any is read
            log_files(args.log)
        except NotALog as err:
            raise CliError(str(err), EXIT_USAGE) from err
    try:
        if not mcap and len(args.log) > 1:
            raise ValueError("one CARMEN log or bag at a time (several files: MCAP logs of a run)")
        if args.ros2:
            from service.ros2.bags import BagError
            from service.ros2.bags import scans_with_poses as bag_scans

            topics = (args.scan_topic, args.pose_topic)
            try:  # the scans read twice (the extent, then the cells) rather than held
                grid = build_grid(lambda: bag_scans(log, *topics), resolution=args.resolution)
            except BagError as err:
                raise ValueError(str(err)) from err
        elif mcap:
            grid = build_grid(_run_scans(args.log, args.from_map), resolution=args.resolution)
        else:
            carmen = read_carmen(log, max_range=args.max_range)
            if carmen.cut:
                print(f"rlutf map build: warning: {log}: {carmen.cut}", file=sys.stderr)
            grid = build_grid(carmen.scans, resolution=args.resolution)
        if args.save_grid:
            save_grid(grid, args.save_grid)
            print(f"wrote {args.save_grid}")
        mid = args.map_id or map_id_from_name(log.name)
        offset = args.surface_offset
        if offset is None:
            offset = BUILT_SURFACE_CELLS * grid.resolution
        result = grid_to_map(grid, map_id=mid, surface_offset=offset, **_options(args))
    except (MapImportError, OSError, ValueError, LogError) as err:
        print(f"rlutf map build: {err}", file=sys.stderr)
        return EXIT_FAILURE
    area = result.polygons.geometry.area
    if area < DEFAULT_MIN_AREA:  # smaller than a robot: few of the log's beams had a return
        print(
            f"rlutf map build: warning: the map holds {area:.2f} m2 of free space, less than "
            f"{DEFAULT_MIN_AREA:g} m2: few of the log's beams had a return (a range that is not "
            "finite, or at or beyond the scanner's maximum or --max-range, is no return); "
            "check the log",
            file=sys.stderr,
        )
    return _finish(args, result)


def _cell_flags(args: argparse.Namespace) -> None:
    """Refuse the flags bounded by a cell (``--surface-offset``, ``--simplify``) before the
    log is read."""
    cell = args.resolution
    if args.surface_offset is not None and args.surface_offset >= 0.5 * cell:
        raise CliError(
            f"--surface-offset {args.surface_offset:g}: must be less than half a cell "
            f"({0.5 * cell:g} m at --resolution {cell:g})",
            EXIT_USAGE,
        )
    if args.simplify is not None and args.simplify > cell:
        raise CliError(
            f"--simplify {args.simplify:g}: must be at most a cell ({cell:g} m at --resolution "
            f"{cell:g})",
            EXIT_USAGE,
        )


def _run_scans(given: list[Path], map_id: str | None) -> Any:
    """What reads the posed scans of the MCAP logs ``given`` (files or folders) recorded at one
    time (:func:`service.maps.mapimport.build_grid` reads them twice rather than hold them): the
    runs of the processes of one ``rlutf serve`` (or of a fleet's instances) together, but not
    runs of two times (two starts of a service, maybe two buildings under one map id)."""
    from service.cli.present import unfinished
    from service.logs.mcapmaps import scans_with_poses
    from service.logs.runs import group_runs, log_files, recordings

    files = log_files(given)
    unfinished("map build", given, files, "not read")
    runs = group_runs(files)
    groups = recordings(runs) or [runs]  # no message at all: said by scans_with_poses
    if len(groups) > 1:
        listed = "; ".join(
            f"{k}: " + ", ".join(f"{r.label}: {' '.join(map(str, r.files))}" for r in group)
            for k, group in enumerate(groups, 1)
        )
        raise ValueError(
            f"the logs hold {len(groups)} recordings made at different times ({listed}): a "
            "map is built from one of them (the runs of one start of rlutf serve, one per "
            "process, are one recording)"
        )
    files = [f for run in groups[0] for f in run.files]
    return lambda: scans_with_poses(files, map_id)  # read twice: the extent, then the cells


def _why(err: BaseException) -> str:
    """The operating system's reason under ``err`` (``No such file or directory``)."""
    cause = err.__cause__
    return (getattr(cause, "strerror", None) or str(cause or err)) if cause else str(err)


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
            data = json.loads(path.read_text(encoding="utf-8"))
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
                return EXIT_FAILURE
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
        data = json.loads(replies[0].payload.to_bytes())
    try:
        title = f"{data.get('map_id', path.stem)} v{data.get('version', '?')}"
        render_map(data, args.out, title=title)
    except MapFileError as err:  # the checks passed, the file system refused (/proc, full)
        raise CliError(
            f"--out {args.out}: cannot write the file ({_why(err)}); choose another"
        ) from err
    except (MapImportError, ValueError, KeyError, TypeError) as err:
        print(f"rlutf map show: not a map: {err}", file=sys.stderr)
        return EXIT_FAILURE
    print(f"wrote {args.out}")
    return EXIT_OK
