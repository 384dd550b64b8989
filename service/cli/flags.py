"""Flag groups and exit codes shared by the command groups, and the client session they open.

Zenoh flags are named like zenoh's own tools (``--mode``, ``--listen``, ``--connect``,
``--config``); the service's settings flags feed :func:`service.config.load_settings`.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from service.cli.errors import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_USAGE,
    UNREACHABLE_HINT,
    CliError,
    zenoh_text,
)

__all__ = [
    "EXIT_FAILURE",
    "EXIT_OK",
    "EXIT_USAGE",
    "client",
    "load",
    "number",
    "seconds",
    "timeout_flag",
    "usable_folder",
    "writable",
]


def number(
    kind: Callable[[str], float] = float,
    *,
    minimum: float | None = None,
    above: float | None = None,
    maximum: float | None = None,
) -> Callable[[str], Any]:
    """An argparse ``type`` that reads a finite number within bounds; a bad one is refused with
    the bounds (argparse names the flag)."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not {'a whole number' if kind is int else 'a number'}"
            ) from None
        # an int has no infinity, and one past a float's range makes isfinite overflow
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r}: give a finite number")
        if above is not None and value <= above:
            raise argparse.ArgumentTypeError(f"{text}: must be more than {_bound(above)}")
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"{text}: must be at least {_bound(minimum)}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"{text}: must be at most {_bound(maximum)}")
        return value

    parse.__name__ = kind.__name__  # argparse's "invalid <name> value" fallback
    return parse


def _bound(value: float) -> str:
    """A bound as a person reads it: a whole number in full (``18446744073709551615``, not
    ``1.84467e+19``), any other as ``:g``."""
    return str(value) if isinstance(value, int) else f"{value:g}"


#: A TCP port (0: any free one).
PORT = number(int, minimum=0, maximum=65535)

#: A ROS_DOMAIN_ID: 0 to 232, the range the setting ros2.domain_id takes (service.config).
ROS_DOMAIN_ID = number(int, minimum=0, maximum=232)

#: The seed of a simulated fleet: numpy's generators take no negative one, and the ROS 2 wire
#: carries it in 64 bits (service.sim.wire).
SEED = number(int, minimum=0, maximum=2**64 - 1)


def writable(path: Path, flag: str) -> None:
    """Refuse an output path that cannot be written (before any work is done).

    Raises:
        CliError: naming the flag, the path and the fix.
    """
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise CliError(f"{flag} {path}: is a folder; give a file name in it", EXIT_USAGE)
    if not folder.is_dir():
        raise CliError(
            f"{flag} {path}: the folder {folder} does not exist; create it or choose another",
            EXIT_USAGE,
        )
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise CliError(
            f"{flag} {path}: not writable ({_denied(folder)}); choose a path you may write",
            EXIT_USAGE,
        )


def _denied(path: Path) -> str:
    """Why ``path`` cannot be written, as a user reads it: on a read-only file system (a
    read-only mount or container layer) or, else, permission denied."""
    try:
        read_only = bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        read_only = False
    return "on a read-only file system" if read_only else "permission denied"


def usable_folder(path: Path, flag: str) -> None:
    """Create the folder, or refuse one that cannot be created or written (its nearest existing
    part is a file, or not writable).

    Raises:
        CliError: naming the flag, the path and the fix.
    """
    part = path.absolute()
    try:
        while not part.exists() and part != part.parent:
            part = part.parent
    except OSError as err:  # a name no file system takes, a loop of links
        raise CliError(
            f"{flag} {path}: cannot create the folder ({err.strerror or err}); choose another",
            EXIT_USAGE,
        ) from err
    if not part.is_dir():
        raise CliError(
            f"{flag} {path}: {part} is a file, not a folder; choose another folder", EXIT_USAGE
        )
    if not os.access(part, os.W_OK | os.X_OK):
        raise CliError(
            f"{flag} {path}: cannot write in {part} ({_denied(part)}); choose a folder you "
            "may write",
            EXIT_USAGE,
        )
    try:  # what the checks cannot see (a read-only or virtual file system) refuses it here
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CliError(
            f"{flag} {path}: cannot create the folder ({err.strerror or err}); choose another",
            EXIT_USAGE,
        ) from err


#: Longest wait a flag takes, seconds (about 31 years): Python's timed waits stop at
#: ``threading.TIMEOUT_MAX`` (about 292 years) and zenoh's at 2**64 s, past which they raise.
MAX_WAIT_S = 1e9


def seconds(*, minimum: float | None = None, above: float | None = None) -> Callable[[str], Any]:
    """An argparse ``type`` for a wait in seconds: finite, within bounds, at most
    :data:`MAX_WAIT_S`."""
    return number(minimum=minimum, above=above, maximum=MAX_WAIT_S)


def timeout_flag(p: argparse.ArgumentParser, default: float = 3.0, what: str = "answers") -> None:
    """Add ``--timeout SECONDS`` (more than 0) with its help."""
    p.add_argument(
        "--timeout",
        type=seconds(above=0),
        default=default,
        metavar="SECONDS",
        help=f"seconds to wait for {what} (default {default:g})",
    )


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
        + (" (default: the -c file's, else tcp/127.0.0.1:7447)" if client else ""),
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
        type=number(int, minimum=-1),
        metavar="N",
        help="worker processes (-1: one per core this process may use, its "
        "container's CPU limit included, the default; 0: in-process thread)",
    )
    p.add_argument(
        "--processes",
        type=number(int, minimum=-1, maximum=64),
        metavar="N",
        help="N full service processes, each owning a share of the robots, behind this one "
        "(router and map store); 0: this process localizes, with --workers; -1 (default): one "
        "per usable core in router mode, unless there is one core, a --foxglove-port or "
        "--workers (then 0)",
    )
    p.add_argument(
        "--metrics-port",
        type=PORT,
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
        type=ROS_DOMAIN_ID,
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
        CliError: the configuration is invalid or the settings file cannot be read.
    """
    from service.config import load_settings

    settings = checked_settings(
        lambda: load_settings(
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
            processes=getattr(args, "processes", None),
            metrics_port=args.metrics_port,
            metrics_addr=args.metrics_addr,
            foxglove_port=getattr(args, "foxglove_port", None),
            foxglove_addr=getattr(args, "foxglove_addr", None),
            ros2=_ros2_overrides(args),
        )
    )
    return _with_file(settings)


def with_file_endpoints(settings: Any) -> Any:
    """A tool's ``settings``: the file's endpoints (in its mode) where -e gives none, else
    :data:`DEFAULT_CONNECT`."""
    settings = _with_file(settings)
    if not settings.connect:
        settings = settings.model_copy(update={"connect": [DEFAULT_CONNECT]})
    return settings


def _with_file(settings: Any) -> Any:
    """``settings`` with what its zenoh file states where no setting is given
    (:func:`service.live.sessions.with_file`); as they are when zenoh cannot read the file
    (:func:`zenoh_file_config` names it before anything starts)."""
    if settings.zenoh_config is None:
        return settings
    import zenoh

    from service.live.sessions import with_file

    try:
        return with_file(settings)
    except zenoh.ZError:
        return settings


def checked_settings(make: Callable[[], Any]) -> Any:
    """``make()`` with its errors (settings file, values) as a :class:`CliError`."""
    from pydantic import ValidationError

    from service.config import SettingsFileError

    try:
        return make()
    except SettingsFileError as err:
        raise CliError(str(err), EXIT_USAGE) from err
    except ValidationError as err:
        raise CliError(_invalid(err), EXIT_USAGE) from err


def _invalid(err: Any) -> str:
    """A pydantic ValidationError of the settings in a few lines, naming each setting."""
    source = os.environ.get("RLUTF_SETTINGS")
    where = f"settings file {source}, " if source else ""
    lines = [f"invalid configuration (from the {where}RLUTF_* environment or the flags):"]
    problems = err.errors()
    for e in problems[:5]:
        loc = ".".join(str(p) for p in e["loc"]) or "(the whole file)"
        msg = "unknown setting" if e["type"] == "extra_forbidden" else e["msg"]
        got = repr(e.get("input"))
        lines.append(f"  {loc}: {msg} (got {got[:60] + '...' if len(got) > 60 else got})")
    if len(problems) > 5:
        lines.append(f"  ... and {len(problems) - 5} more")
    lines.append("fix these values; `rlutf config` prints the settings in effect")
    return "\n".join(lines)


def client(args: argparse.Namespace) -> Any:
    """The settings and an open client session of a tool's :func:`zenoh_flags` (``client``).

    Raises:
        CliError: the settings are invalid or no zenoh router is reachable.
    """
    import zenoh

    from service.config import Settings

    given = {"connect": args.connect} if args.connect else {}
    if args.prefix:
        given["prefix"] = args.prefix
    settings = checked_settings(
        lambda: Settings(mode=args.mode or "client", listen=[], zenoh_config=args.config, **given)
    )
    settings = with_file_endpoints(settings)
    config = zenoh_file_config(settings)
    # A tool asks once: a file made for the service (connect.timeout_ms -1: retry for ever, as
    # deploy/zenoh's) must not make it wait for ever when the router is down.
    config.insert_json5("connect/timeout_ms", "0")
    config.insert_json5("connect/exit_on_failure", "true")
    try:
        return settings, zenoh.open(config)
    except zenoh.ZError as err:
        raise CliError(
            f"cannot reach zenoh at {', '.join(settings.connect)} ({zenoh_text(err)}); "
            + UNREACHABLE_HINT
        ) from err


#: Where the tools look for a running service when neither -e nor a -c file says.
DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def zenoh_file_config(settings: Any) -> Any:
    """The zenoh configuration of ``settings`` (a bad ``-c/--config`` file: :class:`CliError`)."""
    import zenoh

    from service.live.sessions import zenoh_config

    try:
        cfg = zenoh_config(settings)
    except zenoh.ZError as err:
        endpoint = _bad_endpoint(settings)
        if endpoint is not None:
            raise CliError(endpoint, EXIT_USAGE) from err
        if settings.zenoh_config is None:  # no file: the flags' (or settings') values
            raise CliError(
                f"zenoh refuses the configuration of the flags ({' '.join(zenoh_text(err).split())}"
                "); check -m/--mode, -l/--listen and -e/--connect",
                EXIT_USAGE,
            ) from err
        raise CliError(
            f"zenoh config file {settings.zenoh_config}{_json5_problem(zenoh_text(err))}; fix "
            "it (JSON5, as zenohd reads it) or leave out -c/--config",
            EXIT_USAGE,
        ) from err
    endpoint = _bad_endpoint(settings)  # a port zenoh takes here and fails to open later
    if endpoint is not None:
        raise CliError(endpoint, EXIT_USAGE)
    return cfg


#: Where each endpoint setting is listened on or connected to, and an endpoint of its kind.
_ENDPOINT_FLAGS = (
    ("listen", "-l/--listen", "tcp/0.0.0.0:7447"),
    ("connect", "-e/--connect", "tcp/127.0.0.1:7447"),
)


def _bad_endpoint(settings: Any) -> str | None:
    """The first endpoint of ``settings`` that zenoh does not take, said with its flag and the
    form of one (``None``: every endpoint is one)."""
    import json

    import zenoh

    for name, flag, example in _ENDPOINT_FLAGS:
        for endpoint in getattr(settings, name):
            port = endpoint.split("?")[0].split("#")[0].rpartition(":")[2]
            try:
                zenoh.Config().insert_json5(f"{name}/endpoints", json.dumps([endpoint]))
                if port.isdigit() and int(port) > 65535:  # zenoh takes it, and fails to open it
                    raise zenoh.ZError(f"port {port}")
            except zenoh.ZError:
                over = port.isdigit() and int(port) > 65535
                what = f"port {port} is over 65535" if over else "not a zenoh endpoint"
                return f"{flag} {endpoint}: {what}; give PROTOCOL/HOST:PORT, e.g. {example}"
    return None


def _json5_problem(text: str) -> str:
    """``, line L, column C: what`` from a JSON5 parser's multi-line report."""
    import re

    where = re.search(r"-->\s*(\d+):(\d+)", text)
    what = re.search(r"^\s*=\s*(.+)$", text, re.MULTILINE)
    if where is None:
        return ": " + " ".join(text.split())
    return f", line {where[1]}, column {where[2]}: " + (what[1] if what else "not valid JSON5")
