"""Replay: the service's computation over a log's inputs, with no Zenoh.

The inputs of any file in the WIRE.md layout, whoever wrote it, are fed in ``log_time`` order
through the same code the live service runs: :class:`service.maps.book.MapBook` takes the maps
(schema ``rlutf.Map`` on ``{prefix}/maps/{map_id}``) and registers the accepted ones with
:class:`service.engine.FleetEngine`, which takes the initial poses, relocalize requests,
odometry and scans (schemas ``rlutf.InitialPose``, ``rlutf.Relocalize``, ``rlutf.Odometry``,
``rlutf.LaserScan``; the robot id is read from the topic) with their ``log_time`` as receive
time. The same inputs and configuration give the same pose payloads, byte for byte.

Overload: under load the live service drops a robot's unprocessed scan when a newer one arrives,
and records an Event ``scan_dropped`` (``stamp_ns`` = the dropped scan's stamp) on
``{prefix}/robots/{robot}/events``. Replay reads those events first and skips the same scans
(per robot and stamp), so live and replay stay identical whatever the load was.

The output holds the inputs, the recorded ``scan_dropped`` events, the recomputed poses and
events (``log_time`` = the receive time of the input they answer), the Foxglove views, the
configuration used (``rlutf.config``), ``rlutf.replay`` metadata naming the inputs, and
``rlutf.run`` metadata (:mod:`service.logs.runs`): a replay is a run of its own (instance
``replay``, ``replayed_run`` naming the run it recomputed).

One replay is one run: inputs from several runs (files whose ``rlutf.run`` names different
runs) raise :class:`MixedRuns`, since merging them would carry each robot's state from one run
into the next; :func:`service.logs.runs.group_runs` sorts files into runs first.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from schemas import (
    InitialPose,
    LaserScan,
    Odometry,
    PoseEstimate,
    Relocalize,
    SchemaError,
    decode,
)
from service.engine import FleetEngine
from service.keys import Keys
from service.logs.completeness import Completeness, check_run
from service.logs.dropped import EVENT_SCHEMA, LiveDrops
from service.logs.foxglove import FoxgloveConverter
from service.logs.mcapfile import DEFAULT_CHUNK_SIZE, LogWriter, Record
from service.logs.mcapread import (
    LogError,
    LogFile,
    UnreadableConfig,
    map_topic,
    merged_messages,
    robot_topic,
)
from service.logs.posematch import PoseMatch, PoseRecord
from service.logs.replayconfig import ReplayConfig, resolve
from service.logs.runs import RUN_METADATA, RunTag, new_run_id, run_tag
from service.maphealth import MapHealthEngine, ScanEvidence
from service.maps.book import MapBook, MapRejected

log = logging.getLogger(__name__)

INPUT_MODELS: dict[str, type[LaserScan | Odometry | InitialPose | Relocalize]] = {
    "rlutf.LaserScan": LaserScan,
    "rlutf.Odometry": Odometry,
    "rlutf.InitialPose": InitialPose,
    "rlutf.Relocalize": Relocalize,
}
MAP_SCHEMA = "rlutf.Map"
POSE_SCHEMA = "rlutf.PoseEstimate"
MAPHEALTH_SCHEMA = "rlutf.MapHealth"
#: Replay hands the scans' map health evidence on once per this much log time, as workers do.
HEALTH_HANDOVER_NS = 1_000_000_000
REPLAYED = frozenset({*INPUT_MODELS, MAP_SCHEMA, POSE_SCHEMA})
REPLAY_METADATA = "rlutf.replay"

REPLAY_INSTANCE = "replay"
"""The ``instance`` of a replay's ``rlutf.run`` metadata."""

Progress = Callable[[int], None]
"""Called with the number of messages just handled."""


@dataclass
class ReplayResult:
    """What a replay found and computed.

    Attributes:
        config: the configuration it ran with.
        match: the recorded poses matched to the recomputed ones as the replay went
            (:func:`service.logs.audit.audit_match` is the audit): counts, not poses.
        keep: whether the poses and odometry are kept below (``replay(keep=...)``); a long
            log's poses take more memory than a machine has (2 KB a pose), its match does not.
        recorded: poses found in the inputs, per robot, in log order (kept only).
        recomputed: poses computed by the replay, per robot, in order (kept only).
        odometry: ``(stamp_ns, x, y, theta)`` per robot (kept only).
        initial_poses: ``(stamp_ns, map_id, x, y, theta)`` per robot (kept only).
        maps: newest accepted Map payload per map id.
        maphealth: the recomputed MapHealth payloads per map id, in order (the newest only
            unless kept).
        inputs: input messages handled (maps included).
        dropped: scans skipped because they were dropped live.
        rejected: inputs rejected as invalid (the live service would not have recorded them).
        unreadable_poses: recorded poses that are not valid PoseEstimates.
        out: the output file, if one was written.
    """

    config: ReplayConfig
    match: PoseMatch = field(default_factory=PoseMatch)
    keep: bool = True
    recorded: dict[str, list[PoseRecord]] = field(default_factory=lambda: defaultdict(list))
    recomputed: dict[str, list[PoseRecord]] = field(default_factory=lambda: defaultdict(list))
    odometry: dict[str, list[tuple[int, float, float, float]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    initial_poses: dict[str, list[tuple[int, str, float, float, float]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    maps: dict[str, bytes] = field(default_factory=dict)
    maphealth: dict[str, list[bytes]] = field(default_factory=lambda: defaultdict(list))
    inputs: int = 0
    dropped: int = 0
    rejected: int = 0
    unreadable_poses: int = 0
    out: Path | None = None
    completeness: Completeness = field(default_factory=Completeness)
    """What of the inputs was not read, and how they compare with their manifests."""
    gap_ns: int | None = None
    """When the first recording gap began (Event ``recording_resumed`` or ``recorder_overflow``):
    the log lacks inputs from then on, so poses after it cannot be recomputed as they were."""


class MixedRuns(LogError):
    """The inputs of one replay belong to several runs."""


def _source_run(logs: Sequence[LogFile]) -> str | None:
    """The run the inputs belong to (``None``: files without ``rlutf.run``).

    Raises:
        MixedRuns: they belong to several.
    """
    runs: dict[Path, str | None] = {}
    for lf in logs:
        tag = run_tag(lf)
        runs[lf.path] = tag.run_id if tag is not None else None
    distinct = sorted(set(runs.values()), key=str)
    if len(distinct) > 1:
        names = ", ".join(f"{p.name}: {r or 'no rlutf.run'}" for p, r in runs.items())
        raise MixedRuns(
            f"the inputs belong to {len(distinct)} runs ({names}); replaying them together "
            "would carry each robot's state from one run into the next: replay each run on "
            "its own (rlutf replay sorts its inputs into runs)"
        )
    return distinct[0] if distinct else None


def pose_record(payload: bytes, log_time_ns: int = 0) -> PoseRecord:
    """A PoseRecord from a PoseEstimate payload (``log_time_ns``: when its input came).

    Raises:
        SchemaError: not a valid PoseEstimate.
    """
    p = decode(PoseEstimate, payload)
    return PoseRecord(
        p.robot_id, p.stamp_ns, p.map_id, p.x, p.y, p.theta, p.status, payload, log_time_ns
    )


def _prefix_hint(logs: Sequence[LogFile]) -> str | None:
    for lf in logs:
        for ch in lf.channels():
            where = robot_topic(ch.topic) if ch.schema_name in INPUT_MODELS else None
            if where is not None:
                return where.prefix
    return None


class _Run:
    """One pass over the inputs."""

    def __init__(
        self,
        result: ReplayResult,
        drops: LiveDrops,
        writer: LogWriter | None,
        owns: Callable[[str], bool] | None = None,
        count_shared: bool = True,
    ) -> None:
        cfg = result.config
        self.result = result
        self.owns = owns
        self.count_shared = count_shared
        self.drops = drops
        self.writer = writer
        self.evidence = ScanEvidence()
        self.engine = FleetEngine(
            Keys(cfg.prefix), cfg.localizer, cfg.event_interval_ns, cfg.limits, self.evidence
        )
        self.health = MapHealthEngine(Keys(cfg.prefix))
        self.handed_ns: int | None = None
        self.book = MapBook(cfg.max_map_bytes, cfg.map_limits)
        self.maps_seen: set[tuple[str, int, bytes]] = set()
        self.evictions: list[tuple[int, str]] = []  # (log_time_ns, robot), oldest first
        self._next_eviction = 0

    def handle(self, rec: Record) -> None:
        # Robots the live service evicted are forgotten at the same point of the inputs.
        while (
            self._next_eviction < len(self.evictions)
            and self.evictions[self._next_eviction][0] <= rec.log_time_ns
        ):
            self.engine.forget(self.evictions[self._next_eviction][1])
            self._next_eviction += 1
        if rec.schema_name == POSE_SCHEMA:
            try:
                pose = pose_record(rec.payload)
            except SchemaError:
                self.result.unreadable_poses += self.count_shared
                return
            if self.owns is not None and not self.owns(pose.robot):
                return
            self.result.match.recorded(pose)
            if self.result.keep:
                self.result.recorded[pose.robot].append(pose)
        elif rec.schema_name == MAP_SCHEMA:
            self._map(rec)
        else:
            self._input(rec)

    def _write(self, rec: Record) -> None:
        if self.writer is not None:
            self.writer.write(rec)

    def _map(self, rec: Record) -> None:
        where = map_topic(rec.topic)
        seen = (rec.topic, rec.log_time_ns, rec.payload)
        if where is None or seen in self.maps_seen:
            return  # rotated files each start with the maps recorded before them
        self.maps_seen.add(seen)
        self.result.inputs += self.count_shared
        try:
            loaded = self.book.offer(where[1], rec.payload, rec.log_time_ns)
        except MapRejected as err:
            self.result.rejected += self.count_shared
            if self.count_shared:
                log.warning("map on %s rejected: %s", rec.topic, err)
            return
        self._write(rec)
        if loaded is not None:
            assert loaded.world is not None  # checked in this process
            self.engine.register_map(
                loaded.map_id, loaded.version, loaded.world, loaded.received_ns
            )
            self.finish_health(rec.log_time_ns)  # the old version's last evidence first
            self.health.register_map(loaded.map_id, loaded.version, loaded.world)
            self.result.maps[loaded.map_id] = loaded.payload

    def _input(self, rec: Record) -> None:
        where = robot_topic(rec.topic)
        if where is None or (self.owns is not None and not self.owns(where.robot)):
            return
        model = INPUT_MODELS[rec.schema_name]
        try:
            msg = decode(model, rec.payload, max_bytes=self.result.config.max_payload_bytes)
        except SchemaError as err:
            self.result.rejected += 1
            log.warning("%s on %s rejected: %s", rec.schema_name, rec.topic, err)
            return
        self.result.inputs += 1
        self._write(rec)
        robot = where.robot
        keep = self.result.keep
        if isinstance(msg, Odometry):
            if keep:
                self.result.odometry[robot].append((msg.stamp_ns, msg.x, msg.y, msg.theta))
        elif isinstance(msg, InitialPose):
            if keep:
                self.result.initial_poses[robot].append(
                    (msg.stamp_ns, msg.map_id, msg.x, msg.y, msg.theta)
                )
        elif isinstance(msg, LaserScan) and (
            dropped := self.drops.take(robot, msg.stamp_ns, rec.log_time_ns)
        ):
            if isinstance(dropped, Record):  # an older service's log: its Event, at its scan
                self._write(dropped)
            self.result.dropped += 1
            return
        try:
            outputs = self.engine.handle(robot, msg, rec.log_time_ns)
        except Exception:  # as the live workers do: one bad update never stops the others
            log.exception("update of %s failed", robot)
            return
        for out in outputs:
            if out.kind == "rejected":  # over a limit (service.guard): its Event follows
                self.result.rejected += 1
            if out.kind not in ("pose", "event"):
                continue
            schema = POSE_SCHEMA if out.kind == "pose" else EVENT_SCHEMA
            self._write(Record(out.key, schema, out.payload, rec.log_time_ns, out.stamp_ns))
            if out.kind == "pose":
                pose = pose_record(out.payload, rec.log_time_ns)
                self.result.match.recomputed(pose)
                if keep:
                    self.result.recomputed[robot].append(pose)
        self._health(rec.log_time_ns)

    def _health(self, now_ns: int, force: bool = False) -> None:
        """Hand the evidence on once a second of log time; write the MapHealth that is due."""
        if self.handed_ns is None:
            self.handed_ns = now_ns
        if force or now_ns - self.handed_ns >= HEALTH_HANDOVER_NS:
            self.handed_ns = now_ns
            self.health.merge(self.evidence.take())
        for out in self.health.due(now_ns):
            self._write(Record(out.key, MAPHEALTH_SCHEMA, out.payload, now_ns, out.stamp_ns))
            if self.result.keep:
                self.result.maphealth[out.map_id].append(out.payload)
            else:
                self.result.maphealth[out.map_id] = [out.payload]

    def finish_health(self, now_ns: int) -> None:
        """The evidence not handed on yet, and a MapHealth of it (the end of the inputs)."""
        self._health(now_ns + self.health.interval_ns, force=True)


def run_config(
    inputs: Sequence[Path], settings_file: Path | None = None, assignments: Sequence[str] = ()
) -> ReplayConfig:
    """The configuration :func:`replay` runs the inputs with (the recorded one, with
    ``settings_file`` and ``assignments`` over it).

    Raises:
        service.logs.mcapread.LogError: an input is missing, not MCAP, or damaged.
        service.logs.replayconfig.ReplayConfigError: the configuration is invalid.
    """
    with ExitStack() as stack:
        logs = [stack.enter_context(LogFile(p)) for p in inputs]
        return _config(logs, settings_file, assignments)


def _config(
    logs: Sequence[LogFile], settings_file: Path | None, assignments: Sequence[str]
) -> ReplayConfig:
    try:
        recorded = next((c for c in (lf.config() for lf in logs) if c is not None), None)
    except UnreadableConfig as err:
        if settings_file is None and not assignments:
            raise
        log.warning("%s; replaying on the defaults, --settings and --set", err)
        recorded = None
    return resolve(
        recorded,
        prefix_hint=_prefix_hint(logs),
        settings_file=settings_file,
        assignments=assignments,
    )


def replay(
    inputs: Sequence[Path],
    out: Path | None = None,
    *,
    settings_file: Path | None = None,
    assignments: Sequence[str] = (),
    config: ReplayConfig | None = None,
    foxglove: bool = True,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    progress: Progress | None = None,
    on_total: Callable[[int], None] | None = None,
    keep: bool = True,
    owns: Callable[[str], bool] | None = None,
    count_shared: bool = True,
) -> ReplayResult:
    """Replay the inputs of one or more logs (merged in ``log_time`` order).

    Args:
        inputs: log files, e.g. the rotated files of one run in order.
        out: where to write the output log (written as ``OUT.part``, renamed when complete);
            ``None`` writes nothing.
        settings_file: settings merged over the recorded configuration.
        assignments: ``KEY=VALUE`` overrides applied last.
        config: use this configuration instead of resolving one.
        foxglove: add the Foxglove views to the output.
        chunk_size: uncompressed chunk size of the output, bytes.
        progress: called as messages are handled.
        on_total: called once with the number of messages to handle.
        keep: keep every pose and odometry reading in the result (plots, tests); without, the
            result holds the audit's counts (``match``) and memory stays flat however long
            the log.
        owns: replay only the robots for which it is true (their inputs and recorded poses;
            every map): robots are localized apart, so an audit may be split between processes
            by robot (:mod:`service.logs.split`). Default: every robot.
        count_shared: count what belongs to no robot (maps, unreadable poses) in the result;
            false in all but one of the processes an audit is split between.

    Raises:
        service.logs.mcapread.LogError: an input is missing, not MCAP, or damaged.
        MixedRuns: the inputs belong to several runs.
        service.logs.replayconfig.ReplayConfigError: the configuration is invalid.
    """
    with ExitStack() as stack:
        logs = [stack.enter_context(LogFile(p)) for p in inputs]
        source_run = _source_run(logs)
        if config is None:
            config = _config(logs, settings_file, assignments)
        result = ReplayResult(config, keep=keep)
        evictions: list[tuple[int, str]] = []
        gaps: list[int] = []
        drops = LiveDrops(logs, evictions, gaps, out is not None, owns)
        result.gap_ns = min(gaps, default=None)
        result.match = PoseMatch(result.gap_ns)
        if on_total is not None:
            on_total(sum(lf.count(REPLAYED) for lf in logs))
        part = out.with_name(out.name + ".part") if out is not None else None
        stream = stack.enter_context(open(part, "wb")) if part is not None else None
        try:
            converter = FoxgloveConverter() if foxglove else None
            writer = LogWriter(stream, converter, chunk_size) if stream is not None else None
            run_id = new_run_id()
            if writer is not None:
                writer.write_config(config.settings)
                tag = RunTag(
                    run_id,
                    REPLAY_INSTANCE,
                    time.time_ns(),
                    0,
                    extra=(("replayed_run", source_run or ""),),
                )
                writer.write_metadata(RUN_METADATA, tag.to_metadata())
                writer.write_metadata(
                    REPLAY_METADATA,
                    {
                        "inputs": json.dumps([str(p) for p in inputs]),
                        "assignments": json.dumps(list(assignments)),
                        "settings_file": str(settings_file or ""),
                    },
                )
                writer.write_all(drops.records)
            run = _Run(result, drops, writer, owns, count_shared)
            run.evictions = sorted(evictions)
            last_ns = 0
            for rec in merged_messages(logs, REPLAYED):
                run.handle(rec)
                last_ns = rec.log_time_ns
                if progress is not None:
                    progress(1)
            if writer is not None:
                writer.write_all(drops.left())
            run.finish_health(last_ns)
            result.match.end_ns = last_ns
            result.completeness = check_run(logs)
            if writer is not None and stream is not None:
                writer.write_manifest(run_id, 0, last=True)
                writer.finish()
                stream.flush()
                os.fsync(stream.fileno())
        except BaseException:
            if part is not None:
                part.unlink(missing_ok=True)
            raise
    if part is not None and out is not None:
        os.replace(part, out)
        result.out = out
    return result
