"""Whether a bag's odometry is in the frames the ``map`` -> odom written for it names.

``rlutf replay BAG --ros2 --ros2-out OUT`` writes ``map`` -> ``--odom-frame`` on ``tf``: the
estimated pose of ``--base-frame`` composed with the inverse of the bag's odometry. A bag whose
``nav_msgs/Odometry`` is in another frame (``wheel_odom``) is replayed right, but that transform
names a frame the bag's tf tree lacks, so the tree written does not connect; one whose odometry
is of a child frame that the bag's ``tf_static`` puts elsewhere in the plane than the base frame
gives a ``map`` -> odom off by that offset (the live front door says both:
:mod:`service.ros2.frames`). With the odometry read from ``tf`` (``--odom-tf``), a bag whose tf
carries it under other frames (``wheel_odom`` -> ``base_footprint``) has none at all: it is
replayed without odometry and no ``map`` -> odom is written; so is one whose odometry's topic
carries no odometry at all. Each is a warning in the tool's output, naming the frames seen and
the flag to give. A bag without the odometry's topic is refused, naming the flag to give: another
Odometry topic it has, or ``--odom-tf`` when its tf carries the odometry (as the live front door
says of a robot with no Odometry: :mod:`service.ros2.odomwatch`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from itertools import islice

from schemas import SchemaError
from service.keys import printable
from service.ros2 import convert
from service.ros2.frames import FRAME_CHARS, PAIRS_KEPT, Pair, displaced, odometry_like
from service.ros2.statictf import StaticFrames

#: Messages of a bag's tf looked at for its odometry when the odometry's topic is missing.
TF_LOOKED_AT = 1000


class BagOdometryFrames:
    """The frames of a bag's odometry, counted, and the warnings they call for.

    Args:
        topic: the odometry's topic (``Odometry``, or ``tf`` with ``odom_tf``).
        odom_tf: whether the odometry is ``odom_frame`` -> ``base_frame`` on ``tf``.
        global_frame: the parent frame of the ``map`` -> odom written.
        odom_frame: its child, the odometry's frame (``--odom-frame``).
        base_frame: the frame whose pose is estimated (``--base-frame``).
        kept: distinct ``(parent, child)`` counted at most (a bag's frame ids are any text).
    """

    def __init__(
        self,
        topic: str,
        odom_tf: bool,
        global_frame: str,
        odom_frame: str,
        base_frame: str,
        kept: int = PAIRS_KEPT,
    ) -> None:
        self.topic = topic
        self.odom_tf = odom_tf
        self.global_frame = global_frame
        self.odom_frame = odom_frame
        self.base_frame = base_frame
        self.kept = kept
        self.found = 0
        self.seen: dict[Pair, int] = {}  # in the order first seen

    def add(self, found: int, frames: Iterable[Pair]) -> None:
        """One message of the odometry's topic: the odometry readings it gave and its frames
        (an Odometry's ``header.frame_id`` and ``child_frame_id``; a TFMessage's transforms)."""
        self.found += found
        skipped = {(self.global_frame, self.odom_frame), (self.odom_frame, self.base_frame)}
        for parent, child in frames:
            pair = (parent[:FRAME_CHARS], child[:FRAME_CHARS])
            if self.odom_tf and pair in skipped:
                continue  # the odometry itself, or a map -> odom recorded with it
            if pair in self.seen:
                self.seen[pair] += 1
            elif len(self.seen) < self.kept:
                self.seen[pair] = 1

    def warnings(self, static: StaticFrames) -> list[str]:
        """What is wrong with the frames seen, one line each (``static``: the bag's tf_static)."""
        if not self.found:
            return [self._missing()]
        if self.odom_tf:
            return []
        out = []
        others: dict[str, int] = {}
        for (parent, _c), n in self.seen.items():
            if parent != self.odom_frame:
                others[parent] = others.get(parent, 0) + n
        if others:
            out.append(self._other_frame(others))
        for _p, child in self.seen:
            offset = None if child == self.base_frame else static.offset(self.base_frame, child)
            if offset is not None and displaced(offset):
                out.append(self._displaced_child(child, offset))
                break
        return out

    def no_topic(self, types: Mapping[str, str], tf: str, tf_messages: Iterable[bytes]) -> str:
        """What to give when the bag has no topic ``topic``: another Odometry topic it has, or
        ``--odom-tf`` when its ``tf`` carries the odometry (in its first :data:`TF_LOOKED_AT`
        messages, ``tf_messages``, read only then).

        Args:
            types: the bag's topics and their types.
            tf: the tf topic ``--odom-tf`` reads (the one in the scan's namespace).
            tf_messages: the CDR of its messages.
        """
        listed = ", ".join(f"{printable(t)} ({ty})" for t, ty in sorted(types.items()))
        odometry = sorted(t for t, ty in types.items() if ty == convert.ODOMETRY)
        fixes = [f"--odom-topic {printable(t)}" for t in odometry]
        if self.odom_tf:
            fixes = [f"{f} without --odom-tf" for f in fixes]
        elif types.get(tf) == convert.TF_MESSAGE:
            found = self._on_tf(islice(tf_messages, TF_LOOKED_AT))
            if found is not None:
                fixes.insert(0, self._tf_flags(tf, found))
        fix = f". Give {', or '.join(fixes)}" if fixes else ", and no odometry elsewhere"
        return f"no topic {printable(self.topic)} to read the odometry from (topics: {listed}){fix}"

    def _on_tf(self, messages: Iterable[bytes]) -> Pair | None:
        best = None
        for raw in messages:
            try:
                pairs = convert.tf_frames(raw)
            except SchemaError:
                continue
            found = odometry_like(pairs, self.global_frame, self.odom_frame, self.base_frame)
            if found == (self.odom_frame, self.base_frame):
                return found
            best = best or found
        return best

    def _tf_flags(self, tf: str, found: Pair) -> str:
        parent, child = printable(found[0]), printable(found[1])
        flags = "--odom-tf"
        flags += f" --odom-frame {parent}" if found[0] != self.odom_frame else ""
        flags += f" --base-frame {child}" if found[1] != self.base_frame else ""
        return f"{flags} ({printable(tf)} carries {parent} -> {child})"

    def _listed(self, counts: dict[str, int]) -> str:
        return ", ".join(f"'{printable(f)}' ({n} messages)" for f, n in counts.items())

    def _other_frame(self, others: dict[str, int]) -> str:
        odom, seen = self.odom_frame, self._listed(others)
        first = printable(next(iter(others)))
        return (
            f"the odometry on {printable(self.topic)} is in frame {seen}, not '{odom}' "
            f"(--odom-frame): its poses are right, but the {self.global_frame} -> {odom} "
            f"written with --ros2-out names a frame the bag's tf tree lacks, so it does not "
            f"connect. Give --odom-frame {first}"
        )

    def _displaced_child(self, child: str, offset: tuple[float, float, float]) -> str:
        x, y, yaw = offset
        child_, base = printable(child), self.base_frame
        return (
            f"the odometry on {printable(self.topic)} is of frame '{child_}', not '{base}' "
            f"(--base-frame), and the bag's tf_static puts '{child_}' at x {x:.3f} m, y "
            f"{y:.3f} m, yaw {yaw:.3f} rad from '{base}': the {self.global_frame} -> "
            f"{self.odom_frame} written with --ros2-out is off by that offset. Give "
            f"--base-frame {child_}"
        )

    def _missing(self) -> str:
        odom, base = self.odom_frame, self.base_frame
        without = (
            f"the bag is replayed without odometry, and no {self.global_frame} -> {odom} is "
            "written with --ros2-out"
        )
        topic = printable(self.topic)
        if not self.odom_tf:
            return f"no odometry: {topic} carries no valid nav_msgs/Odometry: {without}"
        seen = ", ".join(
            f"{printable(p)} -> {printable(c)} ({n} times)" for (p, c), n in self.seen.items()
        )
        fixes = [f"--base-frame {printable(c)}" for p, c in self.seen if p == odom]
        fixes += [f"--odom-frame {printable(p)}" for p, c in self.seen if c == base]
        fix = f" Give {' or '.join(fixes)}" if fixes else ""
        carries = f"carries {seen}, but" if seen else "carries"
        return (
            f"no odometry: {topic} {carries} no {odom} -> {base} (--odom-frame -> --base-frame): "
            f"{without}.{fix}"
        )


class LaserFrames:
    """The scans' frames that a bag's ``tf_static`` does not link to the base frame, counted.

    Such a scan is taken at the base, as the live front door takes it, where the live service
    logs it and counts it in health; a bag's replay said nothing, and a bag recorded without
    its ``tf_static`` (or with it on another topic) was localized with the laser at the base:
    every pose off by the laser's mount, without a word.

    Args:
        frames: the bag's static transforms (filled as it is read).
        base_frame: the frame whose pose is estimated (``--base-frame``).
        static_topic: the ``tf_static`` topic read.
    """

    def __init__(self, frames: StaticFrames, base_frame: str, static_topic: str) -> None:
        self.frames = frames
        self.base_frame = base_frame
        self.static_topic = static_topic
        self.scans = 0
        self.unlinked: Counter[str] = Counter()
        self.topics: Mapping[str, str] = {}  # the bag's, with types, when the reader sets them

    def offset(self, frame: str) -> tuple[float, float, float] | None:
        """The pose of a scan's ``frame`` in the base frame; ``None`` (counted) when unlinked."""
        self.scans += 1
        found = self.frames.offset(self.base_frame, frame)
        key = frame[:FRAME_CHARS]
        if found is None and (key in self.unlinked or len(self.unlinked) < PAIRS_KEPT):
            self.unlinked[key] += 1
        return found

    def warnings(self, topics: Mapping[str, str] | None = None) -> list[str]:
        """What to say of the scans taken at the base (``topics``: the bag's, with types)."""
        topics = self.topics if topics is None else topics
        if not self.unlinked:
            return []
        n = sum(self.unlinked.values())
        common = self.unlinked.most_common(4)
        listed = ", ".join(f"'{printable(f)}' ({k} scans)" for f, k in common)
        others = sorted(
            t for t, ty in topics.items() if ty == convert.TF_MESSAGE and t.endswith("tf_static")
        )
        others = [printable(t) for t in others if t != self.static_topic]
        has = "the bag has no such topic" if self.static_topic not in topics else "it does not"
        hint = f"; the bag's tf_static is on {', '.join(others)}" if others else ""
        return [
            f"{n} of {self.scans} scans were taken at '{self.base_frame}' (--base-frame): their "
            f"frame {listed} is not linked to it by {printable(self.static_topic)} ({has}){hint}: "
            "poses are off by the laser's mount; record the robot's tf_static with its scans, "
            "or give --base-frame the frame the scans are in"
        ]
