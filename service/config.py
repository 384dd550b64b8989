"""Effective configuration: defaults, an optional file, ``RLUTF_*`` environment variables, flags.

Later sources win: a value given as a command-line flag beats the environment, which beats the
settings file (``--settings FILE`` or ``RLUTF_SETTINGS``; JSON, TOML or YAML), which beats the
defaults. Nested localizer parameters use a double underscore in the environment, for example
``RLUTF_LOCALIZER__EPSILON=0.004``. Lists accept JSON or comma-separated text
(``RLUTF_CONNECT=tcp/10.0.0.5:7447,tcp/10.0.0.6:7447``).
"""

from __future__ import annotations

import json
import os
import socket
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    JsonConfigSettingsSource,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
    YamlConfigSettingsSource,
)

from rlutf.localizer import LocalizerConfig
from rlutf.map import MapLimits
from schemas import ID_PATTERN
from service.guard import Limits, Seconds
from service.infile import read_regular
from service.yamlfile import SETTINGS_MAX_BYTES, load_yaml, problem, unique_keys, where

ZenohMode = Literal["router", "peer", "client"]


def _default_instance() -> str:
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in socket.gethostname())
    return f"{host[:40] or 'rlutf'}-{os.getpid()}"


class _EnvDomainId(str):
    """$ROS_DOMAIN_ID as given, checked by :class:`Ros2Settings` (defaults are validated)."""


def _ros_domain_id() -> Any:  # an int, or the variable as given
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return _EnvDomainId(value) if value else 0


class Ros2Robot(BaseModel):
    """Per-namespace settings of the ROS 2 front door (``ros2.robots``, keyed by namespace)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot_id: str | None = Field(
        None, pattern=f"^{ID_PATTERN}$", description="Robot id (default: the namespace)."
    )
    map_id: str | None = Field(
        None, pattern=f"^{ID_PATTERN}$", description="Map of this robot (default: ros2.map_id)."
    )
    distro: Literal["auto", "humble", "jazzy"] | None = Field(
        None, description="Key naming of this robot (default: ros2.distro)."
    )


class Ros2Settings(BaseModel):
    """The ROS 2 front door (rmw_zenoh): ``--ros2``, ``ros2.*``, ``RLUTF_ROS2__*``."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)

    enabled: bool = Field(False, description="Serve ROS 2 robots on rmw_zenoh's keys.")
    domain_id: int = Field(
        default_factory=_ros_domain_id, ge=0, le=232, description="ROS_DOMAIN_ID (default 0)."
    )
    map_id: str | None = Field(
        None, pattern=f"^{ID_PATTERN}$", description="Map ROS robots are localized on."
    )
    odom_source: Literal["odom", "tf"] = Field(
        "odom", description="Odometry from nav_msgs/Odometry (odom) or odom -> base on tf (tf)."
    )
    scan_topic: str = Field("scan", description="LaserScan topic, relative to the namespace.")
    odom_topic: str = Field("odom", description="Odometry topic, relative to the namespace.")
    initialpose_topic: str = Field("initialpose", description="Initial pose topic.")
    pose_topic: str = Field("amcl_pose", description="Output PoseWithCovarianceStamped topic.")
    tf_topic: str = Field("tf", description="TF topic (read for odom_source=tf, written).")
    tf_static_topic: str | None = Field(
        "tf_static", description="Static TF topic the laser's pose is read from (null: off)."
    )
    map_topic: str | None = Field(
        None, description="OccupancyGrid topic to import maps from (off unless given)."
    )
    global_localization_service: str | None = Field(
        "reinitialize_global_localization",
        description="std_srvs/srv/Empty service, relative to the namespace, that relocalizes the "
        "robot globally on its map, as AMCL's (null: off).",
    )
    global_frame: str = Field("map", description="Frame of poses and initial poses.")
    odom_frame: str = Field("odom", description="The odometry frame.")
    base_frame: str = Field("base_footprint", description="The robot's base frame.")
    odom_wait_s: float = Field(
        0.1,
        ge=0,
        description="Longest a scan waits for the odometry at its stamp (as AMCL's tf filter), s.",
    )
    publish_tf: bool = Field(True, description="Publish map -> odom on the robot's tf.")
    diagnostics_topic: str | None = Field(
        "diagnostics",
        description="DiagnosticArray topic each pose's localization_score and deviation_range "
        "go out on, relative to the namespace (null: off).",
    )
    transform_tolerance_s: float = Field(
        1.0, ge=0, description="map -> odom is stamped this far ahead (AMCL's default), s."
    )
    root_robot: str = Field(
        "robot", pattern=f"^{ID_PATTERN}$", description="Robot id of topics with no namespace."
    )
    distro: Literal["auto", "humble", "jazzy"] = Field(
        "auto",
        description="Key naming to publish with: auto (learned from the robot's keys), humble "
        "(TypeHashNotSupported) or jazzy (RIHS01, Jazzy and later).",
    )
    robots: dict[str, Ros2Robot] = Field(
        default_factory=dict, description="Per-namespace overrides, keyed by namespace."
    )

    @field_validator("domain_id", mode="before")
    @classmethod
    def _domain_from_env(cls, value: Any, info: Any) -> Any:
        if isinstance(value, _EnvDomainId):  # refused as $ROS_DOMAIN_ID, with the front door
            valid = value.isdigit() and int(value) <= 232
            if info.data.get("enabled") and not valid:
                raise ValueError(
                    f"ROS_DOMAIN_ID={str(value)!r} in the environment is no ROS domain id (0 "
                    "to 232): fix it, or give --ros-domain-id or ros2.domain_id"
                )
            return int(value) if valid else 0
        return value

    def robot(self, namespace: str) -> Ros2Robot:
        """The overrides of a namespace (with or without slashes)."""
        return self.robots.get(namespace.strip("/")) or Ros2Robot()


class Settings(BaseSettings):
    """Every setting of the service, with its unit; see ``rlutf config``."""

    model_config = SettingsConfigDict(
        env_prefix="RLUTF_", env_nested_delimiter="__", extra="forbid", frozen=True
    )

    # Zenoh, named like zenoh's own tools.
    mode: ZenohMode = Field("router", description="Zenoh mode: router, peer or client.")
    listen: Annotated[list[str], NoDecode] = Field(
        default_factory=lambda: ["tcp/[::]:7447"], description="Zenoh listen endpoints."
    )
    connect: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Zenoh endpoints to connect to."
    )
    zenoh_config: Path | None = Field(None, description="A zenoh JSON5 configuration file.")
    multicast_scouting: bool = Field(False, description="Zenoh multicast scouting.")

    prefix: str = Field(
        "rlutf", pattern=r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$", description="Key prefix."
    )
    instance: str = Field(
        default_factory=_default_instance,
        pattern=f"^{ID_PATTERN}$",
        description="Name of this instance (liveliness and health keys).",
    )

    store_dir: Path = Field(Path("store"), description="Folder of the embedded map store.")
    no_store: bool = Field(False, description="Do not host the embedded map storage.")
    state_dir: Path = Field(
        Path("store/state"),
        description="Folder of the durable pose state (default: 'state' in the store folder).",
    )
    no_state: bool = Field(False, description="Keep no durable pose state across restarts.")
    map_health: bool = Field(
        True,
        description="Count the scans' disagreement with the maps and publish MapHealth on "
        "{prefix}/maphealth/{map_id} (off: nothing counted, nothing published).",
    )
    state_interval_s: Seconds = Field(
        1.0, gt=0, description="Seconds between two writes of the pose state (when changed)."
    )
    resume_max_age_s: Seconds = Field(
        300.0,
        gt=0,
        description="A robot whose last pose before a restart is older than this is "
        "relocalized globally on its map instead of resuming from it, seconds.",
    )
    record_dir: Path = Field(Path("logs"), description="Folder of the MCAP recordings.")
    no_record: bool = Field(False, description="Do not record MCAP logs.")
    record_max_bytes: int = Field(256 * 1024 * 1024, gt=0, description="Rotate logs at size.")
    record_max_seconds: Seconds = Field(3600.0, gt=0, description="Rotate logs after seconds.")
    record_queue: int = Field(
        20000,
        gt=0,
        description="Recorder queue length, messages (those of 16 kB or more: 256 MiB at most).",
    )
    record_views: bool = Field(
        False,
        description="Also record the Foxglove views (map, scans, poses, tf) in the live logs; "
        "off, `rlutf log views` or `rlutf replay` writes them from a log.",
    )

    workers: int = Field(
        -1,
        ge=-1,
        description="Worker processes; -1: one per usable core (CPU affinity, container CPU "
        "quota); 0: threads.",
    )
    intake: Literal["callback", "loop"] = Field(
        "callback",
        description="How robot inputs come in: 'callback', a Zenoh callback per sample; "
        "'loop', a Zenoh FIFO channel that one thread drains (with --workers 0 that thread "
        "also runs the robots' updates: no thread hand-off per input).",
    )
    intake_wait_s: float = Field(
        0.01,
        ge=0.0001,
        le=0.1,
        description="With intake 'loop' (each process of the default layout): how long the "
        "loop waits, once it has taken in and answered everything, before it looks again. "
        "What comes meanwhile is answered in one round, back to back, which costs less CPU per "
        "scan than answering each scan as it comes, at up to this much more latency.",
    )
    processes: int = Field(
        -1,
        ge=-1,
        le=64,
        description="Service processes behind this one (each a full instance owning a share "
        "of the robots, named INSTANCE-pK; this one routes and holds the map store); 0: this "
        "process localizes, with its workers; -1: one per usable core where there are two or "
        "more, in router mode, with no live view and no workers asked for, else 0.",
    )
    worker_threads: int = Field(
        4,
        ge=1,
        le=64,
        description="Threads per worker: one updates the robots, the others those that may "
        "take long (relocalizing or lost), so that a relocalization holds up only its own "
        "robot; one robot's updates always run in order; 1: one update at a time per worker.",
    )
    worker_nice: int = Field(
        0,
        ge=0,
        le=19,
        description="Niceness the worker processes add to the service's (0: none). Past what "
        "the cores hold, a positive value keeps the main process, which takes every input in "
        "and counts what it drops, ahead of the workers: the excess is dropped, counted, in the "
        "robots' mailboxes instead of waiting in the bus's queues (answered seconds late, or "
        "lost uncounted), at the cost of fewer scans answered (BENCHMARKS.md, 'Overload').",
    )
    metrics_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="Port of the Prometheus endpoint /metrics (off unless given; 0: any free "
        "port).",
    )
    metrics_addr: str = Field("0.0.0.0", description="Address the metrics endpoint listens on.")
    foxglove_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="Port of the live view, a Foxglove WebSocket server an operator opens in the "
        "Foxglove app (off unless given; 0: any free port).",
    )
    foxglove_addr: str = Field(
        "127.0.0.1",
        description="Address the live view listens on (0.0.0.0 to open it from other hosts).",
    )
    foxglove_rate_hz: float = Field(
        10.0, gt=0, le=100, description="Most refreshes a second of each robot's live view."
    )
    max_payload_bytes: int = Field(
        1_000_000, gt=0, description="Largest accepted payload of a robot's message, bytes."
    )
    max_map_bytes: int = Field(
        64 * 1024 * 1024,
        gt=0,
        description="Largest accepted Map payload, bytes (maps have their own limit: a site's "
        "map is megabytes of JSON).",
    )
    max_map_area: float = Field(
        100_000.0,
        gt=0,
        description="Largest area of a map's bounding box, square metres: the wall index, the "
        "distance field and the relocalization grid cost memory in proportion to it (about "
        "3 kB per square metre in each service process whose robots use the map, and map "
        "health's evidence grid up to 1.5 kB more while map_health is on).",
    )
    max_map_vertices: int = Field(
        4_000_000,
        gt=0,
        description="Most vertices of a map (validation and walls cost time in proportion).",
    )
    map_timeout_s: Seconds = Field(2.0, gt=0, description="Timeout of a map get, seconds.")
    max_stamp_ahead_s: Seconds = Field(
        60.0,
        gt=0,
        description="Inputs and followed poses stamped further ahead of the service's clock are "
        "rejected (Event stamp_rejected): a far-future stamp would pin a robot's pose.",
    )
    robot_idle_s: Seconds = Field(
        3600.0,
        gt=0,
        description="A robot that sends nothing for this long is evicted (Event robot_evicted).",
    )
    max_robots: int = Field(
        10_000,
        gt=0,
        description="Robot ids an instance holds at once; inputs for more get robot_limit.",
    )
    event_interval_s: Seconds = Field(
        1.0,
        ge=0,
        description="Least time between two events of one code for one robot, or for puts of "
        "one map.",
    )
    handover_timeout_s: Seconds = Field(
        1.0,
        gt=0,
        description="Timeout of the liveliness get at start and of the pose get that seeds a "
        "robot acquired with no pose in memory, seconds.",
    )
    handover_odom_s: Seconds = Field(
        5.0,
        gt=0,
        description="Odometry kept per robot owned by another instance (by stamp, seconds), to "
        "anchor the seed when this instance takes the robot over.",
    )
    join_warmup_s: Seconds = Field(
        0.5,
        ge=0,
        description="When other instances are live at start: seconds to follow the fleet's "
        "poses and odometry before declaring the liveliness token and taking robots over.",
    )
    join_grace_s: float = Field(
        0.3,
        ge=0,
        le=10,
        description="When other instances are live at start: seconds the robots taken over "
        "wait, once the token is declared, for their previous owner's last answers.",
    )
    ros2: Ros2Settings = Field(
        default_factory=Ros2Settings, description="The ROS 2 front door (rmw_zenoh)."
    )
    localizer: LocalizerConfig = Field(
        default_factory=LocalizerConfig, description="RLuTF parameters (see rlutf.LocalizerConfig)."
    )
    limits: Limits = Field(
        default_factory=Limits,
        description="What inputs may hold beyond the schema (see service.guard.Limits).",
    )

    @field_validator("listen", "connect", mode="before")
    @classmethod
    def _split_list(cls, value: Any) -> Any:
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                try:
                    return json.loads(text)
                except RecursionError:  # pydantic reports a ValueError as the field's error
                    raise ValueError("a list nested deeper than a list of endpoints") from None
            return [v.strip() for v in text.split(",") if v.strip()]
        return value

    @model_validator(mode="before")
    @classmethod
    def _state_in_store(cls, data: Any) -> Any:
        # The default follows store_dir, so the state lands on the store's volume.
        if isinstance(data, dict) and data.get("state_dir") is None:
            return {**data, "state_dir": Path(str(data.get("store_dir") or "store")) / "state"}
        return data

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        path = os.environ.get("RLUTF_SETTINGS")
        if path:
            sources.append(_file_source(settings_cls, Path(path)))
        return tuple(sources)

    def map_limits(self) -> MapLimits:
        """What a map may cost (``max_map_area``, ``max_map_vertices``)."""
        return MapLimits(self.max_map_area, self.max_map_vertices)

    def service_processes(self, cores: int | None = None) -> int:
        """The service processes ``processes`` asks for, ``-1`` resolved (``cores``: the usable
        cores, :func:`service.cores.usable_cores` when ``None``).

        ``-1`` is one process per usable core (BENCHMARKS.md, "The default layout: processes": on
        two cores the layout of processes answers more scans with a shorter tail and less
        memory, and loses none uncounted) except where the other layout is what serves: one
        core (a host process with nothing to spread), ``--mode client`` or ``peer`` (an instance
        of a fleet deployment, scaled by its replicas), a live view (``--foxglove-port``: each
        process sees only its own robots) or ``workers`` set (the layout of workers asked for).
        """
        if self.processes >= 0:
            return self.processes
        if (
            self.mode != "router"
            or self.foxglove_port is not None
            or "workers" in self.model_fields_set
        ):
            return 0
        if cores is None:
            from service.cores import usable_cores

            cores = usable_cores()
        return cores if cores >= 2 else 0

    def effective(self) -> dict[str, Any]:
        """The configuration as JSON-ready data (what ``rlutf config`` prints)."""
        return self.model_dump(mode="json")


class SettingsFileError(ValueError):
    """A settings file that is missing, of an unknown kind or not well-formed; the message names
    the file, the line where the parser could tell, and the fix."""


def _file_source(settings_cls: type[BaseSettings], path: Path) -> PydanticBaseSettingsSource:
    if not path.is_file():
        what = "not found" if not path.exists() else "is not a regular file"  # a folder, a FIFO
        raise SettingsFileError(
            f"settings file {path} {what}: give an existing file with --settings or RLUTF_SETTINGS"
        )
    suffix = path.suffix.lower()
    sources = {
        ".json": lambda: JsonConfigSettingsSource(settings_cls, json_file=path),
        ".toml": lambda: TomlConfigSettingsSource(settings_cls, toml_file=path),
        ".yaml": lambda: YamlConfigSettingsSource(settings_cls, yaml_file=path),
        ".yml": lambda: YamlConfigSettingsSource(settings_cls, yaml_file=path),
    }
    if suffix not in sources:
        raise SettingsFileError(
            f"settings file {path}: unknown kind {suffix or '(no suffix)'!r}; "
            "name it .json, .toml, .yaml or .yml"
        )
    _check_file(path, suffix)
    return sources[suffix]()


def _check_file(path: Path, suffix: str) -> None:
    """Parse the file as the source will, so that a bad one is named with its line."""
    kind = "YAML" if suffix in (".yaml", ".yml") else suffix[1:].upper()
    try:
        text = read_regular(path, SETTINGS_MAX_BYTES).decode("utf-8")
        if kind == "JSON":
            data: Any = json.loads(text, object_pairs_hook=unique_keys)
        elif kind == "TOML":
            data = tomllib.loads(text)
        else:
            data = load_yaml(text, unique=True)
    except OSError as err:  # over SETTINGS_MAX_BYTES, or unreadable
        raise SettingsFileError(
            f"settings file {path}: cannot read it ({problem(err)}); settings are a few kB"
        ) from err
    except (ValueError, RecursionError, yaml.YAMLError) as err:
        raise SettingsFileError(
            f"settings file {path}{where(err)}: not valid {kind} ({problem(err)}); fix the "
            "file, or leave out --settings and RLUTF_SETTINGS"
        ) from err
    if data is not None and not isinstance(data, dict):
        raise SettingsFileError(
            f"settings file {path}: holds a {type(data).__name__}, not settings; write one "
            "'name: value' per setting at the top level (see `rlutf config`)"
        )


def load_settings(settings_file: Path | None = None, **overrides: Any) -> Settings:
    """Settings from every source; ``overrides`` (flags) win, ``None`` values are ignored.

    Args:
        settings_file: a JSON, TOML or YAML file (else ``RLUTF_SETTINGS`` if set).
        overrides: values from flags.
    """
    if settings_file is not None:
        os.environ["RLUTF_SETTINGS"] = str(settings_file)
    given = {k: v for k, v in overrides.items() if v is not None}
    return Settings(**given)
