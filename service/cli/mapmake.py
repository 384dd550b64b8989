"""``rlutf map import`` and ``rlutf map build``: a Map from an occupancy grid (map_server's
YAML and image) or from logs (CARMEN, the service's MCAP logs, a ROS 2 bag), written, drawn and
put as ``rlutf map`` writes, draws and puts every map."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from service.cli.errors import CliError
from service.cli.flags import EXIT_OK, EXIT_USAGE, client, writable


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
    _within_limits(result.map)
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
                f"--png {args.png}: cannot write the file ({why(err)}); choose another"
            ) from err
        print(f"wrote {args.png}")
    if args.put:
        from service.maps.client import put_map

        settings, session = client(args)
        with session:
            version = args.version if args.version is not None else "next"
            return put_map(session, settings.prefix, out, mid, version)
    return EXIT_OK


def _within_limits(wire: dict[str, Any]) -> None:
    """Refuse a map the service would refuse with the settings in effect (``max_map_area``,
    ``max_map_vertices``, ``max_map_bytes``; defaults, ``RLUTF_*``, ``RLUTF_SETTINGS``), before
    it is written: WIRE.md v1.2 promises that every map import and build write is taken. A grid
    of large extent (a 2 km site at 0.5 m is 16 million cells and a few walls) was written, exit
    0, and only its put refused, once the file was on its way to the site.

    Raises:
        CliError: the figure, the setting and the value that takes it (exit 2).
    """
    from rlutf.errors import MapError
    from rlutf.map import raw_extent
    from service.cli.flags import checked_settings
    from service.config import Settings

    settings = checked_settings(lambda: Settings(mode="client", listen=[]))
    # The positions as the service counts them before it builds anything (Map.from_geojson).
    (x0, y0, x1, y1), vertices = raw_extent(wire["geometry"])
    size = len(json.dumps(wire, separators=(",", ":")))
    try:
        settings.map_limits().check((x0, y0, x1, y1), vertices)
        if size > settings.max_map_bytes:
            raise MapError(
                f"the map is {size} bytes of JSON, more than the limit of "
                f"{settings.max_map_bytes} (setting max_map_bytes)"
            )
    except MapError as err:
        needed = {
            "max_map_area": f"{(x1 - x0) * (y1 - y0):.0f}",
            "max_map_vertices": str(vertices),
            "max_map_bytes": str(size),
        }
        name = next(n for n in needed if n in str(err))
        raise CliError(
            f"{err}: the map store and the service refuse it with the settings in effect, so it "
            f"is not written. For a site this large, give the service and this command a larger "
            f"{name} (RLUTF_{name.upper()}={needed[name]}, or {name} in the settings file; "
            "docs/operations.md, Maps, says the memory it takes), or keep less of the grid "
            "(--component, a cropped image)",
            EXIT_USAGE,
        ) from err


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
    except MapImportError as err:  # the YAML or its image: the input to fix
        print(f"rlutf map import: {err}", file=sys.stderr)
        return EXIT_USAGE
    return _finish(args, result)


def cmd_build(args: argparse.Namespace) -> int:
    """``rlutf map build``."""
    from service.cores import available_memory
    from service.logs.mcapread import LogError
    from service.maps.mapimport import (
        BUILT_SURFACE_CELLS,
        DEFAULT_MAX_RANGE,
        DEFAULT_MIN_AREA,
        MapImportError,
        grid_to_map,
        map_id_from_name,
        max_grid_cells,
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
    _source_flags(args)
    log = args.log[0]
    # half the memory the host has for the grid (16 million cells always)
    cells = {"resolution": args.resolution, "max_cells": max_grid_cells(available_memory())}
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
            from service.ros2.bagframes import LaserFrames
            from service.ros2.bags import BagError, BagTopics
            from service.ros2.bags import scans_with_poses as bag_scans
            from service.ros2.statictf import StaticFrames

            topics = (args.scan_topic, args.pose_topic, args.base_frame)
            static = BagTopics(scan=args.scan_topic).in_namespace("tf_static")
            lasers = LaserFrames(StaticFrames(), args.base_frame, static)

            def scans() -> Any:  # each reading counts the scans put at the base anew
                lasers.scans = 0
                lasers.unlinked.clear()
                return bag_scans(log, *topics, lasers)

            try:  # the scans read twice (the extent, then the cells) rather than held
                grid = _built(capped(scans, args.max_range), log.name, cells)
            except BagError as err:
                raise ValueError(str(err)) from err
            for warning in lasers.warnings():
                print(f"rlutf map build: warning: {warning}", file=sys.stderr)
        elif mcap:
            grid = _built(
                capped(_run_scans(args.log, args.from_map), args.max_range), log.name, cells
            )
        else:
            carmen = read_carmen(
                log, max_range=DEFAULT_MAX_RANGE if args.max_range is None else args.max_range
            )
            if carmen.cut:
                print(f"rlutf map build: warning: {log}: {carmen.cut}", file=sys.stderr)
            grid = _built(carmen.scans, log.name, cells)
        if args.save_grid:
            save_grid(grid, args.save_grid)
            print(f"wrote {args.save_grid}")
        mid = args.map_id or map_id_from_name(log.name)
        offset = args.surface_offset
        if offset is None:
            offset = BUILT_SURFACE_CELLS * grid.resolution
        result = grid_to_map(grid, map_id=mid, surface_offset=offset, **_options(args))
    except (MapImportError, OSError, ValueError, LogError) as err:  # the log: the input to fix
        print(f"rlutf map build: {err}", file=sys.stderr)
        return EXIT_USAGE
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


def _built(scans: Any, name: str, cells: dict[str, Any]) -> Any:
    """``build_grid`` of ``scans``, each reading of the log shown as a progress bar on a
    terminal (minutes for a long bag, with nothing shown before)."""
    from service.cli.buildprogress import reading_scans
    from service.maps.mapimport import build_grid

    with reading_scans(name) as counted:
        return build_grid(counted(scans), **cells)


def capped(scans: Any, max_range: float | None) -> Any:
    """What reads ``scans`` (a function giving them anew) with each scan's range_max at most
    ``max_range`` (``None``: as they are). ``--max-range`` was read for CARMEN logs alone: an
    MCAP log or a bag was built with every range up to its scanner's maximum, in silence."""
    if max_range is None:
        return scans

    def read() -> Iterator[Any]:
        for pose, ranges, angles, range_max in scans():
            yield pose, ranges, angles, min(range_max, max_range)

    return read


def _source_flags(args: argparse.Namespace) -> None:
    """Refuse the flags the kind of LOG given does not read (they were ignored in silence:
    ``--pose-topic`` on an MCAP log, ``--from-map`` on a bag), before it is read."""
    log = args.log[0]
    mcap = not args.ros2 and (log.is_dir() or log.suffix == ".mcap")
    unread = []
    if not args.ros2:
        unread += [
            f
            for f, v, d in (
                ("--scan-topic", args.scan_topic, "/scan"),
                ("--pose-topic", args.pose_topic, "/amcl_pose"),
                ("--base-frame", args.base_frame, "base_footprint"),
            )
            if v != d
        ]
    if not mcap and args.from_map is not None:
        unread.append("--from-map")
    if unread:
        kind = "a bag (--ros2)" if args.ros2 else "MCAP logs" if mcap else "a CARMEN log"
        raise CliError(
            f"{', '.join(unread)}: not read for {kind}: --scan-topic and --pose-topic are a "
            "bag's (with --ros2), --from-map is MCAP logs'; leave them out, or give --ros2 "
            "with a bag",
            EXIT_USAGE,
        )


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


def why(err: BaseException) -> str:
    """The operating system's reason under ``err`` (``No such file or directory``)."""
    cause = err.__cause__
    return (getattr(cause, "strerror", None) or str(cause or err)) if cause else str(err)
