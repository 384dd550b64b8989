"""rosbag2 recordings in and out: a bag's inputs as a replay log, poses as a rosbag2 MCAP.

In: a rosbag2 recording (a bag folder, or a bare ``.mcap`` with ``cdr`` channels and
``ros2msg`` schemas) is read with rosbags' ``AnyReader``; its scans, odometry (``Odometry`` or
the ``odom`` -> base transform on ``tf``) and initial poses are converted (the laser's pose
from the bag's ``tf_static``, when it has one) as the live front
door converts them (:mod:`service.ros2.convert`) and written, with the map and an optional
initial pose, as an MCAP log in the WIRE.md layout, ``log_time`` the bag's receive time. That
log is an ordinary replay input: ``rlutf replay --ros2`` replays it with the service's engine.
Odometry in other frames than the ones given is said in the summary's warnings
(:mod:`service.ros2.bagframes`).

Out: the poses of a replay as a rosbag2 MCAP (``amcl_pose`` and the ``map`` -> ``odom`` on
``tf``, per robot namespace), which ``ros2 bag play`` and Foxglove open.
"""

from __future__ import annotations

import bisect
import contextlib
import logging
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from rlutf.motion import compose
from schemas import (
    SCHEMA_NAMES,
    InitialPose,
    LaserScan,
    Map,
    Odometry,
    PoseEstimate,
    SchemaError,
    decode,
)
from service.infile import not_a_file
from service.keys import Keys, printable
from service.logs.mcapchunks import ChunkTooLarge
from service.logs.mcapfile import LogWriter, Record
from service.logs.mcaprecords import RecordTooLarge, bound_file
from service.ros2 import convert, names
from service.ros2.bagframes import BagOdometryFrames, LaserFrames
from service.ros2.statictf import StaticFrames
from service.ros2.trail import OdometryTrail, map_to_odom

log = logging.getLogger(__name__)

ScanAtPose = tuple[np.ndarray, np.ndarray, np.ndarray, float]


class BagError(Exception):
    """A bag that cannot be read, or that lacks what was asked for."""


@dataclass(frozen=True)
class BagTopics:
    """Where a bag's inputs are and how to read them.

    Attributes:
        scan: the LaserScan topic; its namespace names the robot.
        odom: the Odometry topic (``odom_tf`` false).
        odom_tf: read odometry from ``odom_frame`` -> ``base_frame`` on ``tf`` instead.
        tf: the TF topic (default: ``tf`` in the scan's namespace).
        initialpose: an initial pose topic to read too (default: ``initialpose`` in the
            scan's namespace, when the bag has it).
        global_frame, odom_frame, base_frame: the frames, as Nav2 names them by default.
    """

    scan: str = "/scan"
    odom: str = "/odom"
    odom_tf: bool = False
    tf: str | None = None
    initialpose: str | None = None
    global_frame: str = "map"
    odom_frame: str = "odom"
    base_frame: str = "base_footprint"

    @property
    def namespace(self) -> str:
        """The scan topic's namespace, ``/robot1`` (``/`` for none)."""
        return "/" + "/".join(self.scan.strip("/").split("/")[:-1])

    def in_namespace(self, name: str) -> str:
        """``name`` in the scan's namespace."""
        return names.join_topic(self.namespace, name)


@dataclass
class BagSummary:
    """What a conversion read and left out, and what is wrong with the bag's frames."""

    robot: str
    namespace: str
    counts: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    warnings: list[str] = field(default_factory=list)
    first_ns: int = 0
    last_ns: int = 0


@contextlib.contextmanager
def _reader(bag: Path) -> Iterator[Any]:
    """The bag open for reading; a bag rosbags cannot open (its ``metadata.yaml`` damaged, say)
    is a :class:`BagError`, like one it cannot find."""
    from rosbags.highlevel import AnyReader

    if not bag.exists():  # rosbags says "The following paths are missing: [PosixPath(...)]"
        raise BagError(f"{bag}: no such file or folder (a rosbag2 folder, or its .mcap)")
    for path in [bag, *(sorted(bag.iterdir()) if bag.is_dir() else [])]:
        problem = not_a_file(path)  # rosbags would wait on a FIFO for ever
        if problem is not None:
            raise BagError(f"{path}: not a readable rosbag2 recording: {problem}")
        if path.name.endswith(".mcap") and path.is_file():
            try:  # rosbags reads a record whole, and decompresses a chunk whole, to any size
                bound_file(path)
            except (ChunkTooLarge, RecordTooLarge, OSError) as err:
                raise BagError(f"{path}: not a readable rosbag2 recording: {err}") from err
    try:
        reader = AnyReader([bag], default_typestore=convert.typestore())
        reader.open()
    except Exception as err:  # rosbags raises its own errors per storage, at either step
        raise BagError(f"{bag}: not a readable rosbag2 recording: {err}") from err
    try:
        yield reader
    finally:
        reader.close()


def _on_topic(reader: Any, topic: str) -> Iterator[tuple[Any, int, Any]]:
    """The messages of one topic of an open bag (none when the bag lacks it: rosbags reads
    every topic when given no connection)."""
    conns = [c for c in reader.connections if c.topic == topic]
    if conns:
        yield from _messages(reader, conns)


def _messages(reader: Any, conns: list[Any]) -> Iterator[tuple[Any, int, Any]]:
    """``reader.messages(connections=conns)``, where whatever the reader raises (a damaged bag
    makes rosbags raise anything from ``OverflowError`` to ``struct.error``) is a
    :class:`BagError` that says how far the bag was read."""
    read = 0
    messages = iter(reader.messages(connections=conns))
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as err:  # rosbags' errors on damaged data are not one type
            bag = ", ".join(str(p) for p in reader.paths)
            raise BagError(
                f"{bag}: damaged: {type(err).__name__}: {str(err)[:200]}, after {read} messages "
                "of the topics read (an MCAP bag: `mcap recover` writes its readable part)"
            ) from err
        read += 1
        yield item


def bag_inputs(
    bag: Path,
    out: BinaryIO,
    map_payload: bytes,
    topics: BagTopics,
    *,
    initial: tuple[float, float, float] | None = None,
    robot_id: str | None = None,
    keys: Keys | None = None,
    config: Mapping[str, Any] | None = None,
) -> BagSummary:
    """Write a bag's inputs to ``out`` as an MCAP log in the WIRE.md layout.

    Args:
        bag: the recording.
        out: where the log goes.
        map_payload: the Map the robot is localized on (written first).
        topics: where the inputs are.
        initial: ``(x, y, theta)`` of the robot in the map at the first scan.
        robot_id: the robot's id (default: the scan topic's namespace, ``robot`` for none).
        keys: the key layout.
        config: the configuration to store in the log (``rlutf.config``).

    Raises:
        BagError: the bag is unreadable, or lacks the scan or odometry topic.
    """
    keys = keys or Keys()
    map_msg = decode(Map, map_payload, max_bytes=10**9)
    try:
        robot = robot_id or names.robot_of_namespace(topics.namespace, "robot")
    except names.NamespaceError as err:  # the live service's fix (the settings) is not replay's
        raise BagError(f"{str(err).split(';')[0]}: give the robot's id with --robot ID") from err
    summary = BagSummary(robot, topics.namespace)
    odom_topic = topics.tf or topics.in_namespace("tf") if topics.odom_tf else topics.odom
    pose_topic = topics.initialpose or topics.in_namespace("initialpose")
    static_topic = topics.in_namespace("tf_static")
    wanted = {
        topics.scan: "scan",
        odom_topic: "odom",
        pose_topic: "initialpose",
        static_topic: "tf_static",  # the laser's pose in the base frame
    }
    frames = StaticFrames()
    lasers = LaserFrames(frames, topics.base_frame, static_topic)
    odometry_frames = BagOdometryFrames(
        odom_topic, topics.odom_tf, topics.global_frame, topics.odom_frame, topics.base_frame
    )
    with _reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        present = set(types)
        if topics.scan not in present:
            raise BagError(f"{bag}: no topic {topics.scan} (topics: {', '.join(sorted(present))})")
        if odom_topic not in present:
            tf = topics.tf or topics.in_namespace("tf")
            tf_messages = (bytes(raw) for _c, _t, raw in _on_topic(reader, tf))
            said = odometry_frames.no_topic(types, tf, tf_messages)
            raise BagError(f"{bag}: {said}")
        conns = [c for c in reader.connections if c.topic in wanted]
        writer = LogWriter(out, None)
        if config is not None:
            writer.write_config(config)
        started = False
        for conn, t_ns, raw in _messages(reader, conns):
            kind = wanted[conn.topic]
            if not started:
                started = True
                summary.first_ns = t_ns
                writer.write(
                    Record(keys.map(map_msg.map_id), "rlutf.Map", map_payload, t_ns - 2, t_ns - 2)
                )
            try:
                if kind == "tf_static":
                    _expect(conn.msgtype, convert.TF_MESSAGE)
                    for parent, child, pose in convert.static_transforms(bytes(raw)):
                        frames.add(parent, child, pose)
                    continue
                msgs: Sequence[LaserScan | Odometry | InitialPose]
                if kind == "odom":
                    msgs = _odometry(conn.msgtype, bytes(raw), topics, odometry_frames)
                else:
                    msgs = _convert(kind, conn.msgtype, bytes(raw), map_msg.map_id, topics, lasers)
            except SchemaError as err:
                summary.rejected[f"{conn.topic}: {str(err)[:120]}"] += 1
                continue
            for m in msgs:
                if initial is not None and isinstance(m, LaserScan):
                    x, y, theta = initial
                    ip = InitialPose(
                        stamp_ns=m.stamp_ns, map_id=map_msg.map_id, x=x, y=y, theta=theta
                    )
                    _write(writer, keys, robot, ip, t_ns - 1)
                    summary.counts["initialpose"] += 1
                    initial = None
                _write(writer, keys, robot, m, t_ns)
                summary.counts[type(m).__name__] += 1
            summary.last_ns = t_ns
        writer.finish()
    summary.warnings = odometry_frames.warnings(frames) + lasers.warnings(types)
    if not summary.counts["LaserScan"]:
        on_scan = f"{topics.scan}: "
        why = Counter(
            {k[len(on_scan) :]: n for k, n in summary.rejected.items() if k.startswith(on_scan)}
        )
        raise BagError(f"{bag}: no valid scan on {topics.scan}{_why(why)}")
    if not summary.counts["initialpose"] and not summary.counts["InitialPose"]:
        raise BagError(
            f"{bag}: no initial pose: give --initial-pose X,Y,THETA (none on {pose_topic})"
        )
    return summary


def _convert(
    kind: str, msgtype: str, raw: bytes, map_id: str, topics: BagTopics, lasers: LaserFrames
) -> list[LaserScan | InitialPose]:
    if kind == "scan":
        _expect(msgtype, convert.LASER_SCAN)
        return [convert.laser_scan(raw, offset_of=lasers.offset)]
    _expect(msgtype, convert.POSE_COV)
    return [convert.initial_pose(raw, map_id, topics.global_frame)]


def _odometry(
    msgtype: str, raw: bytes, topics: BagTopics, seen: BagOdometryFrames
) -> list[Odometry]:
    """A message of the odometry's topic as Odometry, its frames counted in ``seen``."""
    if topics.odom_tf:
        _expect(msgtype, convert.TF_MESSAGE)
        found, pairs = convert.odometry_from_tf_in_frames(raw, topics.odom_frame, topics.base_frame)
        seen.add(len(found), pairs)
        return found
    _expect(msgtype, convert.ODOMETRY)
    odom, frame_id, child = convert.odometry_in_frames(raw)
    seen.add(1, [(frame_id, child)])
    return [odom]


def _expect(got: str, want: str) -> None:
    if got != want:
        raise convert.CdrError(f"carries {got}, expected {want}")


def _write(
    writer: LogWriter, keys: Keys, robot: str, msg: LaserScan | Odometry | InitialPose, t: int
) -> None:
    leaf = {LaserScan: "scan", Odometry: "odom", InitialPose: "initialpose"}[type(msg)]
    writer.write(
        Record(
            keys.robot(robot, leaf),
            SCHEMA_NAMES[type(msg)],
            convert.wire_json(msg),
            t,
            msg.stamp_ns,
        )
    )


# ------------------------------------------------------------------------------ out
def write_pose_bag(
    path: Path,
    poses: Mapping[str, list[bytes]],
    odometry: Mapping[str, list[tuple[int, float, float, float]]],
    namespaces: Mapping[str, str],
    *,
    pose_topic: str = "amcl_pose",
    tf_topic: str = "tf",
    global_frame: str = "map",
    odom_frame: str = "odom",
    transform_tolerance_s: float = 0.0,
) -> tuple[int, int]:
    """Write poses as a rosbag2 MCAP folder: ``amcl_pose`` and ``map`` -> ``odom`` per robot.

    Args:
        path: the bag folder to create (must not exist).
        poses: PoseEstimate payloads per robot, in order.
        odometry: ``(stamp_ns, x, y, theta)`` per robot, for ``map`` -> ``odom``.
        namespaces: each robot's namespace (``/`` for none; default ``/{robot}``).
        transform_tolerance_s: how far ahead ``map`` -> ``odom`` is stamped.

    Returns:
        The numbers of ``amcl_pose`` and of ``tf`` messages written (a pose with no odometry
        reading at its stamp gets no ``map`` -> ``odom``).
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = convert.typestore()
    written = transforms = 0
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for robot, payloads in poses.items():
            ns = namespaces.get(robot, f"/{robot}")
            pc = writer.add_connection(
                names.join_topic(ns, pose_topic), convert.POSE_COV, typestore=ts
            )
            tc = writer.add_connection(
                names.join_topic(ns, tf_topic), convert.TF_MESSAGE, typestore=ts
            )
            trail = OdometryTrail(kept=1 << 62)
            for stamp, x, y, theta in odometry.get(robot, []):
                trail.add(stamp, (x, y, theta))
            ahead = int(transform_tolerance_s * 1e9)
            for payload in payloads:
                pose = decode(PoseEstimate, payload)
                writer.write(pc, pose.stamp_ns, convert.amcl_pose(pose, global_frame))
                written += 1
                odom = trail.at(pose.stamp_ns)
                if odom is not None:
                    m_o = map_to_odom([pose.x, pose.y, pose.theta], odom)
                    raw = convert.transform(m_o, pose.stamp_ns + ahead, global_frame, odom_frame)
                    writer.write(tc, pose.stamp_ns, raw)
                    transforms += 1
    return written, transforms


#: How far a stamp goes back, on a bag's pose or scan topic, for a clock reset, ns (less is a
#: message that came late).
CLOCK_RESET_NS = 1_000_000_000


def scans_with_poses(
    bag: Path,
    scan_topic: str,
    pose_topic: str,
    base_frame: str = "base_footprint",
    lasers: LaserFrames | None = None,
) -> Iterator[ScanAtPose]:
    """``(sensor pose, ranges, angles, range_max)`` for each scan of a bag with poses.

    Each scan takes the pose (a ``PoseWithCovarianceStamped``, e.g. ``amcl_pose``) at its
    stamp, interpolated between the two around it; scans outside the poses' span, or with no
    pose within half a second, are left out. The pose is the base's (``base_frame``); the
    sensor's is that composed with the laser's pose in it, from the ``tf_static`` of the scan's
    namespace, as replay reads it (a scan whose frame that tree does not link to the base is
    taken at the base, and counted in ``lasers`` when given: its frames, base frame and topics).

    A clock reset (a stamp more than :data:`CLOCK_RESET_NS` older than the one before it on its
    topic, in the bag's order: a simulation restarted, a robot's clock set back between two
    recordings) starts a new span of poses and of scans, and the scans of the k-th span take
    the poses of the k-th span only: the poses of two spans stamped alike were mixed, and half
    the walls of such a bag's map were drawn from the wrong pose, with no word.

    The bag is read twice: its poses first (a few numbers each, held), then its scans, each
    given as it is read, so a mapping run of hours is never held (a decoded scan is about 3 KB);
    :func:`service.maps.mapimport.build_grid` asks for the scans twice, so a map build reads
    the bag four times.

    Raises:
        BagError: the bag is unreadable or has no scan with a pose.
    """
    trails: list[OdometryTrail] = []
    last: int | None = None
    frames = lasers.frames if lasers else StaticFrames()
    static_topic = BagTopics(scan=scan_topic).in_namespace("tf_static")
    with _reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        if lasers:
            lasers.topics = types
        said = _unposed(bag, types, scan_topic, pose_topic)
        if said:
            raise BagError(said)
        for conn, _t, raw in _on_topic(reader, static_topic):
            with contextlib.suppress(SchemaError):
                _expect(conn.msgtype, convert.TF_MESSAGE)
                for parent, child, offset in convert.static_transforms(bytes(raw)):
                    frames.add(parent, child, offset)
        for conn, _t, raw in _on_topic(reader, pose_topic):
            try:
                m = convert.deserialize(bytes(raw), conn.msgtype)
                p = m.pose.pose
                stamp = convert.stamp_ns(m.header)
                at = (p.position.x, p.position.y, convert.yaw(p.orientation))
            except (SchemaError, AttributeError):
                continue
            if last is None or stamp < last - CLOCK_RESET_NS:
                trails.append(OdometryTrail(kept=1 << 62))
            last = stamp
            trails[-1].add(stamp, at)
    offset_of = lasers.offset if lasers else partial(frames.offset, base_frame)
    span, last = 0, None
    found = 0
    invalid: Counter[str] = Counter()
    if trails:
        with _reader(bag) as reader:
            for _conn, _t, raw in _on_topic(reader, scan_topic):
                try:
                    scan = convert.laser_scan(bytes(raw), offset_of=offset_of)
                except (SchemaError, AttributeError) as err:
                    invalid[str(err)[:200]] += 1
                    continue
                if last is not None and scan.stamp_ns < last - CLOCK_RESET_NS:
                    span += 1
                last = scan.stamp_ns
                if span >= len(trails):
                    continue  # a span of scans with no poses
                trail = trails[span]
                pose_stamps = trail.stamps  # in order
                i = bisect.bisect_left(pose_stamps, scan.stamp_ns)
                near = [pose_stamps[j] for j in (i - 1, i) if 0 <= j < len(pose_stamps)]
                if not near or min(abs(s - scan.stamp_ns) for s in near) > 500_000_000:
                    continue
                if scan.stamp_ns < pose_stamps[0] or scan.stamp_ns > pose_stamps[-1]:
                    continue
                base = trail.at(scan.stamp_ns)
                assert base is not None
                off = scan.sensor_offset
                pose = compose(base, np.array([off.x, off.y, off.theta]))
                ranges = np.array([np.nan if r is None else r for r in scan.ranges])
                angles = scan.angle_min + scan.angle_increment * np.arange(len(ranges))
                found += 1
                yield pose, ranges, angles, scan.range_max
    if not found:
        raise BagError(f"{bag}: no scan on {scan_topic} has a pose on {pose_topic}{_why(invalid)}")


def _unposed(bag: Path, types: Mapping[str, str], scan: str, pose: str) -> str | None:
    """Why a map cannot be built from the bag's topics (one missing, or of another type), with
    the topics that would do; ``None`` when they are there. It said "no scan on /scan has a pose
    on /amcl_pose" of a bag with neither topic."""
    kinds = {
        "--scan-topic": (scan, (convert.LASER_SCAN,)),
        "--pose-topic": (pose, (convert.POSE_COV, convert.ODOMETRY)),
    }
    for flag, (topic, wanted) in kinds.items():
        if types.get(topic) in wanted:
            continue
        fits, want = sorted(t for t, ty in types.items() if ty in wanted), " or ".join(wanted)
        what = f"carries {types[topic]}, not {want}" if topic in types else "is not in the bag"
        give = f"give {flag} {' or '.join(fits)}" if fits else f"the bag has no {want}"
        return f"{bag}: {printable(topic)} ({flag}) {what}; {give}"
    return None


def _why(invalid: Counter[str]) -> str:
    """Why the scans left out were refused, the commonest first: ``""`` for none."""
    if not invalid:
        return ""
    listed = "; ".join(f"{n} scans: {why}" for why, n in invalid.most_common(3))
    return f" ({sum(invalid.values())} scans refused: {listed})"
