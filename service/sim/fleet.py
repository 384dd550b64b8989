"""A plan's robots on Zenoh: the sessions, the map, the start, and the publishing schedule.

:class:`SimFleet` opens the robots' client sessions, puts the map, announces each robot's start
(its first odometry and its InitialPose) and sends one robot's step at a time; :func:`drive`
calls it at the robots' rate, in time order, each robot's phase staggered over the period as
independent robots' scanners are.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import zenoh

from service.cores import available_memory
from service.keys import Keys
from service.sim.plan import FleetPlan, FleetSpec, plan_bytes
from service.sim.wire import RobotWire, map_payload

if TYPE_CHECKING:
    from service.maps.client import Put

JSON = zenoh.Encoding.APPLICATION_JSON
#: Robots per client session by default (1 to 8 sessions).
ROBOTS_PER_SESSION = 12


class SimFleet:
    """The robots of ``plan`` putting ``wire``'s payloads on sessions that ``open_session`` opens.

    Args:
        plan: the fleet.
        wire: its payloads (:class:`~service.sim.wire.JsonWire` or ``CdrWire``).
        open_session: opens one client session to the service.
        sessions: how many sessions the robots share (default: one per 12 robots, 1 to 8).
        keys: the key layout the map is put under.
        congestion_control: of the robots' publishers (Zenoh's default, drop, when ``None``;
            ``BLOCK`` makes a full queue slow the robots instead of losing their messages).
    """

    def __init__(
        self,
        plan: FleetPlan,
        wire: RobotWire,
        open_session: Callable[[], zenoh.Session],
        sessions: int | None = None,
        keys: Keys | None = None,
        congestion_control: Any = None,
    ) -> None:
        self.plan, self.wire, self.keys = plan, wire, keys or Keys()
        robots = len(plan.robots)
        count = sessions or max(1, min(8, robots // ROBOTS_PER_SESSION))
        self.sessions = [open_session() for _ in range(count)]
        self._qos = {} if congestion_control is None else {"congestion_control": congestion_control}
        self._publishers: list[tuple[Any, Any]] = []

    @property
    def operator(self) -> zenoh.Session:
        """The first session, which puts the map and the initial poses."""
        return self.sessions[0]

    def put_map(self) -> bytes:
        """Put the plan's map into the service's store; returns the payload."""
        payload = map_payload(self.plan)
        self.operator.put(self.keys.map(self.plan.spec.map_id), payload, encoding=JSON)
        return payload

    def store_map(self, timeout: float = 5.0) -> Put:
        """Put the plan's map into the store as the next version, unless the store holds these
        walls already, and wait for its answer. Put as version 1 regardless, another ``--seed``'s
        building held under the same id would stay (the same version with other walls changes
        nothing) and every robot would be lost on it."""
        from service.maps.client import NEXT, put_payload

        return put_payload(self.operator, self.keys.prefix, map_payload(self.plan), NEXT, timeout)

    def start(self, t0_ns: int) -> None:
        """Each robot's step 0, stamped ``t0_ns``: its first odometry, then its InitialPose (if
        the plan gives one); and its publishers for the steps to come."""
        w = self.wire
        for i in range(len(self.plan.robots)):
            session = self.sessions[i % len(self.sessions)]
            odom = w.odometry(i, 0, t0_ns)
            session.put(w.key(i, "odom"), odom, attachment=w.attachment(i), encoding=w.encoding)
            initial = w.initial_pose(i, t0_ns)
            if initial is not None:
                self.operator.put(w.key(i, "initialpose"), initial, encoding=w.encoding)
            self._publishers.append(
                (
                    session.declare_publisher(w.key(i, "odom"), encoding=w.encoding, **self._qos),
                    session.declare_publisher(w.key(i, "scan"), encoding=w.encoding, **self._qos),
                )
            )

    def extras(self, step: int, stamp_ns: int) -> int:
        """Put the Relocalize requests and bad input due at ``step``; returns how many."""
        due = self.plan.extras(step)
        for robot, kind in due:
            key, payload = self.wire.extra(robot, kind, stamp_ns)
            self.sessions[robot % len(self.sessions)].put(
                key, payload, attachment=self.wire.attachment(robot), encoding=self.wire.encoding
            )
        return len(due)

    def odometry(self, robot: int, step: int, stamp_ns: int) -> None:
        """Put the robot's odometry of ``step``."""
        w = self.wire
        self._publishers[robot][0].put(
            w.odometry(robot, step, stamp_ns), attachment=w.attachment(robot)
        )

    def scan(self, robot: int, step: int, stamp_ns: int) -> None:
        """Put the robot's scan of ``step``."""
        w = self.wire
        self._publishers[robot][1].put(
            w.scan(robot, step, stamp_ns), attachment=w.attachment(robot)
        )

    def send(self, robot: int, step: int, stamp_ns: int) -> None:
        """The robot's odometry, then its scan, of ``step``."""
        self.odometry(robot, step, stamp_ns)
        self.scan(robot, step, stamp_ns)

    def close(self) -> None:
        """Undeclare the publishers and close the sessions."""
        for odom, scan in self._publishers:
            odom.undeclare()
            scan.undeclare()
        self._publishers.clear()
        for s in self.sessions:
            s.close()


def drive(
    robots: int,
    period_s: float,
    send: Callable[[int, int], None],
    steps: int | None = None,
    stop: threading.Event | None = None,
    on_step: Callable[[int], None] | None = None,
) -> tuple[int, int, float]:
    """Call ``send(robot, step)`` for steps 1, 2, ... of every robot at one step per period.

    Robot ``i``'s step ``k`` is due ``(k - 1 + i / robots)`` periods after the start; calls
    come in time order, late ones without waiting. ``on_step(k)`` is called before step ``k``'s
    first robot.

    Args:
        robots: how many robots.
        period_s: time between a robot's steps, seconds.
        send: sends one robot's step.
        steps: the last step (``None``: until ``stop``).
        stop: ends the run before the next call once set.
        on_step: called at each step's start.

    Returns:
        Calls made, the last step begun, and how far behind its schedule the last call came (s).
    """
    start = time.monotonic()
    calls = 0
    behind = 0.0
    step = 0
    while (steps is None or step < steps) and not (stop is not None and stop.is_set()):
        step += 1
        if on_step is not None:
            on_step(step)
        for i in range(robots):
            if stop is not None and stop.is_set():
                return calls, step, behind
            due = start + (step - 1 + i / robots) * period_s
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            send(i, step)
            calls += 1
            behind = time.monotonic() - due
    return calls, step, behind


def memory_problem(spec: FleetSpec, available: int | None = None) -> str | None:
    """Why the plan of ``spec`` should not be drawn: it would take more than half the memory
    available (``available``: default :func:`available_memory`); ``None`` if it fits."""
    free = available_memory() if available is None else available
    need = plan_bytes(spec)
    if free is None or need <= free // 2:
        return None
    return (
        f"{spec.robots} robots with {_short(spec.poses)} poses of {spec.beams}-beam scans each "
        f"would take about {_short(need / 1e9)} GB for their precomputed scans, and "
        f"{free / 1e9:.1f} GB is available: simulate fewer robots, for less time, or with "
        "fewer beams"
    )


def _short(value: float) -> str:
    """``value`` as it reads: whole or with one decimal, three digits and an exponent past a
    million (``--path-seconds 1e300`` printed a number of 300 digits, twice)."""
    if value >= 1e6:
        return f"{value:.3g}"
    return str(value) if isinstance(value, int) else f"{value:.1f}"


@contextmanager
def drawing_bar(robots: int) -> Iterator[Callable[[], None]]:
    """A progress bar, on a terminal, while ``robots`` simulated robots are drawn: yields what to
    call as each one is (nothing shown elsewhere: the command says when the drawing is done)."""
    if not sys.stdout.isatty():
        yield lambda: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    with Progress(
        "drawing", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), transient=True
    ) as bar:
        task = bar.add_task("robots", total=robots)
        yield lambda: bar.advance(task)
