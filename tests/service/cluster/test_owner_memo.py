"""The owner memo of :class:`Membership` stays bounded whatever robot ids come.

Found by a reviewer flooding a running ``rlutf serve`` with odometry puts on 300,000 made-up
robot ids: its memory grew by about 100 bytes an id and never came back, the owner of every
id asked being remembered until the members changed (with no other instance, never).
"""

from __future__ import annotations

from service.cluster import membership
from service.cluster.membership import Membership, owner_of


def test_the_owner_memo_holds_a_bounded_number_of_robots() -> None:
    m = Membership("a")
    m.update("b", alive=True)
    flood = 100_000
    for i in range(flood):
        m.owner(f"z{i}")
    assert len(m._owners) < flood
    assert len(m._owners) <= membership.OWNERS_MAX
    # still right, for ids remembered or not
    for robot in ("z0", f"z{flood - 1}", "r1"):
        assert m.owner(robot) == owner_of(robot, ["a", "b"])
