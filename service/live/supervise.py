"""What a robot needs to be re-seeded when the worker process that held its localizer dies.

A worker process can die (the kernel's OOM killer, a crash in native code, ``kill -9``): its
robots' localizers die with it. The dispatcher then starts a new process (or moves the robots to
a surviving one) and re-seeds each robot as a restart does (:mod:`service.cluster.ownership`):
from the last pose the service itself published for it, with its odometry anchored at that pose's
stamp, never from anything a client said about its pose.

To keep audits exact, a re-seed is made of ordinary inputs that are recorded like received ones
(the odometry readings from the one at or before the pose's stamp on, then an InitialPose built
from the pose, then the operator's requests the dead worker had not applied), and the scans the
dead worker never answered are recorded as dropped (``scan_dropped``), so that replay, which
never loses a worker, skips them too. An InitialPose resets the robot's localizer, so replay's
robot, which saw the lost inputs too, is in the same state as the new worker's after it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from schemas import InitialPose, PoseEstimate, Relocalize, SchemaError, decode, encode
from service.keys import InputKind
from service.live.worker import Entry

#: Odometry readings kept per robot to anchor a re-seed (a few seconds at 20 Hz).
ODOM_KEPT = 64


def worker_lost(index: int, code: int | None, robots: list[str]) -> str:
    """What the Event ``worker_lost`` says of worker process ``index`` that died with exit
    ``code`` and the ``robots`` re-seeded (the first ten named)."""
    more = f" and {len(robots) - 10} more" if len(robots) > 10 else ""
    shown = ", ".join(robots[:10]) + more
    return (
        f"worker process {index} died (exit code {code}); a new one is starting; "
        f"{len(robots)} robots re-seeded from their last published poses"
        + (f" ({shown})" if robots else "")
        + "; the scans it had not answered are dropped"
    )


@dataclass
class History:
    """A robot's recent inputs and its last published pose, kept by the dispatcher."""

    odometry: deque[Entry] = field(default_factory=lambda: deque(maxlen=ODOM_KEPT))
    request: Entry | None = None  # the last InitialPose or Relocalize received
    pose: bytes | None = None  # the last PoseEstimate published
    pose_received_ns: int = 0  # when the scan it answers was received

    def note_input(self, entry: Entry) -> None:
        """Keep what a re-seed may need of an input handed to the robot's mailbox."""
        if entry.kind == "odom":
            self.odometry.append(entry)
        elif entry.kind in ("initialpose", "relocalize"):
            self.request = entry

    def note_pose(self, payload: bytes, received_ns: int | None) -> None:
        """Keep a pose the service published for the robot."""
        self.pose = payload
        self.pose_received_ns = received_ns or 0

    def reseed(self, lost: list[Entry], clock: Callable[[], int]) -> list[Entry]:
        """The inputs that bring a new localizer to where the lost one was.

        Args:
            lost: the robot's inputs the dead worker had not answered (in order); their scans
                are not among the result (the caller reports them dropped).
            clock: the receive clock: every input returned gets a fresh receive time, in order.

        Returns:
            Odometry from the reading at or before the last pose's stamp on, the seed (an
            InitialPose at the last pose, or a Relocalize when that pose was ambiguous), and
            the requests received after that pose or lost; empty when the robot had neither a
            pose nor a request.
        """
        pose = self._last_pose()
        seed: list[Entry] = []
        odometry = list(self.odometry)
        if pose is not None:
            before = [i for i, e in enumerate(odometry) if e.stamp_ns <= pose.stamp_ns]
            odometry = odometry[before[-1] :] if before else odometry
            message: InitialPose | Relocalize
            if pose.hypotheses:  # ambiguous: its best guess may be the wrong place
                message = Relocalize(stamp_ns=pose.stamp_ns, map_id=pose.map_id)
            else:
                message = InitialPose(
                    stamp_ns=pose.stamp_ns, map_id=pose.map_id, x=pose.x, y=pose.y, theta=pose.theta
                )
            kind: InputKind = "relocalize" if isinstance(message, Relocalize) else "initialpose"
            seed.append(Entry(kind, encode(message), message, 0, message.stamp_ns))
        requests = [e for e in lost if e.kind in ("initialpose", "relocalize")]
        r = self.request
        if r is not None and r not in requests and r.received_ns > self.pose_received_ns:
            requests.insert(0, r)  # applied by the dead worker, but no pose came of it yet
        if not seed and not requests:
            return []
        later = [e for e in lost if e.kind == "odom" and e not in odometry]
        out = [*odometry, *seed, *later, *requests]
        return [Entry(e.kind, e.payload, e.message, clock(), e.stamp_ns) for e in out]

    def _last_pose(self) -> PoseEstimate | None:
        if self.pose is None:
            return None
        try:
            return decode(PoseEstimate, self.pose)
        except SchemaError:  # our own encoding: only a bug gets here
            return None
