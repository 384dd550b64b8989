"""Client tools over Zenoh for a running fleet: poses, health, live instances, the operator's
requests (InitialPose, Relocalize) followed to their outcome, and the fleet's Events.

Nothing here prints: the command line formats what these functions return or hand to their
callbacks.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Literal, NamedTuple

import zenoh

from schemas import (
    Event,
    EventCode,
    Health,
    InitialPose,
    PoseEstimate,
    Relocalize,
    SchemaError,
    decode,
    encode,
)
from service.keys import Keys

JSON = zenoh.Encoding.APPLICATION_JSON


def fetch_poses(
    session: zenoh.Session, prefix: str, robot: str, timeout: float
) -> tuple[list[PoseEstimate], list[str]]:
    """The latest PoseEstimate of one robot (or ``*``: every robot), by robot id, and the keys
    whose answer could not be decoded."""
    poses: dict[str, PoseEstimate] = {}
    bad: list[str] = []
    for reply in session.get(Keys(prefix).pose(robot), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            pose = decode(PoseEstimate, reply.ok.payload.to_bytes())
        except SchemaError:
            bad.append(str(reply.ok.key_expr))
            continue
        old = poses.get(pose.robot_id)
        if old is None or pose.stamp_ns > old.stamp_ns:
            poses[pose.robot_id] = pose
    return [poses[r] for r in sorted(poses)], bad


def fetch_health(
    session: zenoh.Session, prefix: str, instance: str, timeout: float
) -> list[Health]:
    """The Health of each live instance that answers (``*``: all), by instance name."""
    found: list[Health] = []
    for reply in session.get(Keys(prefix).health(instance), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            found.append(decode(Health, reply.ok.payload.to_bytes()))
        except SchemaError:
            continue
    return sorted(found, key=lambda h: h.instance)


def live_instances(session: zenoh.Session, prefix: str, timeout: float = 1.0) -> list[str]:
    """The instances whose liveliness token is declared on ``{prefix}/service/*``."""
    base = f"{prefix}/service/"
    names = {
        str(r.ok.key_expr).removeprefix(base)
        for r in session.liveliness().get(f"{base}*", timeout=timeout)
        if r.ok is not None
    }
    return sorted(names)


def robot_of(prefix: str, events_key: str) -> str | None:
    """The robot of ``{prefix}/robots/{robot}/events``; ``None`` for ``{prefix}/events``."""
    head = f"{prefix}/robots/"
    if events_key.startswith(head) and events_key.endswith("/events"):
        return events_key[len(head) : -len("/events")]
    return None


#: ``(robot or None, event)`` for each Event followed.
EventCallback = Callable[[str | None, Event], None]


def follow_events(
    session: zenoh.Session,
    prefix: str,
    robot: str | None,
    on_event: EventCallback,
    stop: threading.Event,
    seconds: float | None = None,
    on_other: Callable[[str, int, str], None] | None = None,
) -> None:
    """Hand every Event of ``robot`` (``None``: every robot's and the service-wide ones) to
    ``on_event`` as it arrives, until ``stop`` is set or ``seconds`` have passed; anything else
    put on those keys to ``on_other`` (key, bytes, why it is no Event), if given."""
    keys = Keys(prefix)

    def on_sample(sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        try:
            ev = decode(Event, payload)
        except SchemaError as err:
            if on_other is not None:
                on_other(str(sample.key_expr), len(payload), str(err))
            return
        on_event(robot_of(prefix, str(sample.key_expr)), ev)

    wanted = [keys.robot_events(robot)] if robot else [keys.robot_events("*"), f"{prefix}/events"]
    subs = [session.declare_subscriber(k, on_sample) for k in wanted]
    try:
        stop.wait(seconds)
    finally:
        for s in subs:
            s.undeclare()


class Outcome(NamedTuple):
    """How a request ended: ``done`` (the service acted on it), ``refused`` (an Event said why),
    or ``waiting`` (nothing within the time given); the last pose seen, if any."""

    result: Literal["done", "refused", "waiting"]
    pose: PoseEstimate | None
    code: str | None = None  # the refusing Event's code


#: Seconds a relocalization's outcome waits, after the Event ``relocalized``, for a pose.
POSE_AFTER_S = 2.0


def put_request(
    session: zenoh.Session,
    prefix: str,
    robot: str,
    request: InitialPose | Relocalize,
    wait: float,
    on_event: EventCallback,
) -> Outcome:
    """Put an InitialPose or Relocalize for ``robot`` and follow its Events for up to ``wait``
    seconds (0: put only).

    Done means: for a Relocalize, the Event ``relocalized``; for an InitialPose, a pose of the
    robot on the requested map published after the put. Refused: ``map_not_found`` for the
    requested map or the request's key, or ``invalid_message`` for the request's key.
    """
    keys = Keys(prefix)
    kind = "initialpose" if isinstance(request, InitialPose) else "relocalize"
    key = keys.robot(robot, kind)
    if wait <= 0:
        session.put(key, encode(request), encoding=JSON)
        return Outcome("waiting", None)
    # "done", or "refused" with the refusing Event's code
    ended: queue.Queue[tuple[Literal["done", "refused"], str | None]] = queue.Queue()
    last: list[PoseEstimate] = []
    # The Event and the pose of the update that relocalized the robot go out on different
    # paths, either first: after the Event, the outcome's pose is one received after it.
    relocalized, pose_after = threading.Event(), threading.Event()
    failures = {
        (EventCode.MAP_NOT_FOUND, keys.map(request.map_id)),
        (EventCode.MAP_NOT_FOUND, key),
        (EventCode.INVALID_MESSAGE, key),
    }

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            ev = decode(Event, sample.payload.to_bytes())
        except SchemaError:
            return
        on_event(robot, ev)
        if ev.code == EventCode.RELOCALIZED and kind == "relocalize":
            relocalized.set()
            ended.put(("done", None))
        elif (ev.code, ev.key) in failures:
            ended.put(("refused", ev.code))

    def on_pose(sample: zenoh.Sample) -> None:
        try:
            pose = decode(PoseEstimate, sample.payload.to_bytes())
        except SchemaError:
            return
        last[:] = [pose]
        if relocalized.is_set():
            pose_after.set()
        if kind == "initialpose" and pose.map_id == request.map_id:
            ended.put(("done", None))

    subs = [
        session.declare_subscriber(keys.robot_events(robot), on_sample),
        session.declare_subscriber(keys.pose(robot), on_pose),
    ]
    try:
        session.put(key, encode(request), encoding=JSON)
        try:
            result, code = ended.get(timeout=wait)
        except queue.Empty:
            return Outcome("waiting", last[0] if last else None)
        if result == "done" and kind == "relocalize":
            pose_after.wait(POSE_AFTER_S)  # the robot's next scan gives it
        return Outcome(result, last[0] if last else None, code)
    finally:
        for s in subs:
            s.undeclare()
