"""services/neighbours.py keeps every robot's latest pose in slot arrays: the neighbours a
pose block sees (position, radius, velocity from the last two poses, floor, expiry after
``POSE_TTL``) are exactly those of the poses noted, across slot growth and compaction."""

from __future__ import annotations

import numpy as np
from confnav.schemas import Goal, Pose, encode
from confnav.services.keys import Keys
from confnav.services.neighbours import POSE_TTL, Neighbours

K = Keys()


def _pose(rid: str, t_ns: int, x: float, y: float, seq: int = 1) -> Pose:
    return Pose(robot_id=rid, stamp_ns=t_ns, seq=seq, x=x, y=y)


def test_neighbours_positions_velocities_floors_and_expiry() -> None:
    nb = Neighbours(K, default_radius=0.05)
    nb._on_goal(K.robot("a", "goal"), encode(Goal(robot_id="a", ws_id="w1", goal=(0.0, 0.0),
                                                  robot_radius=0.2)))  # fmt: skip
    nb._on_goal(K.robot("b", "goal"), encode(Goal(robot_id="b", ws_id="w2~r0.3",
                                                  goal=(0.0, 0.0), robot_radius=0.3)))  # fmt: skip
    nb.note_pose("a", _pose("a", 1_000_000_000, 1.0, 2.0), now=10.0)
    nb.note_pose("a", _pose("a", 1_500_000_000, 1.5, 1.0, 2), now=10.5)  # v = (1 - 2i) m/s
    nb.note_pose("a", _pose("a", 1_200_000_000, 9.0, 9.0, 3), now=10.6)  # reordered: ignored
    nb.note_pose("b", _pose("b", 1_000_000_000, -1.0, 0.0), now=10.5)
    nb.note_pose("c", _pose("c", 1_000_000_000, 0.0, -1.0), now=10.5)  # no body: every floor
    z, r, v, coop, mover = nb._others("w1", set(), now=10.6)
    assert list(z) == [1.5 + 1j, -1j]
    assert list(r) == [0.2, 0.2]  # c's body is unknown: the largest known on w1, a's
    assert v[0] == (1.5 + 1j - (1 + 2j)) / 0.5 and v[1] == 0
    assert not coop.any() and not mover.any()
    z, _, _, _, _ = nb._others("w2", {"c"}, now=10.6)  # floor of "w2~r0.3"; c excluded
    assert list(z) == [-1 + 0j]
    _, r, _, _, _ = nb._others("w2", {"b"}, now=10.6)  # the filtered robot's body counts
    assert list(r) == [0.3]
    _, r, _, _, _ = Neighbours(K, default_radius=0.05)._others(None, set(), now=0.0)
    assert r.size == 0
    # a served robot is cooperative and counts with velocity 0
    nb.served_many = lambda rids: [rid == "a" for rid in rids]
    _, _, v, coop, _ = nb._others("w1", set(), now=10.6)
    assert list(coop) == [True, False] and v[0] == 0
    # a robot gone for POSE_TTL is forgotten; seen again, it starts without a velocity
    z, *_ = nb._others(None, set(), now=10.5 + POSE_TTL + 0.1)
    assert z.size == 0 and nb._seen == {}
    nb.note_pose("a", _pose("a", 9_000_000_000, 0.0, 0.0, 4), now=20.0)
    assert nb._seen["a"].v == 0 and nb._seen["a"].z == 0


def test_many_robots_grow_and_compact_the_slots() -> None:
    nb = Neighbours(K)
    for i in range(600):  # grows the arrays past 64, 128, 256, 512
        nb.note_pose(f"r{i}", _pose(f"r{i}", 1_000, float(i), 0.0), now=0.0 if i < 500 else 5.0)
    z, *_ = nb._others(None, set(), now=5.0)  # the first 500 expired: slots compacted
    assert sorted(z.real) == [float(i) for i in range(500, 600)]
    assert len(nb._rids) == 100 and set(nb._slot) == {f"r{i}" for i in range(500, 600)}
    nb.note_pose("r550", _pose("r550", 2_000, 550.0, 1.0, 2), now=5.1)
    nb.note_pose("r7", _pose("r7", 1_000, 7.0, 0.0), now=5.1)  # new again after compaction
    seen = nb._seen
    assert seen["r550"].z == 550 + 1j and seen["r7"].z == 7 and len(seen) == 101
    z, *_ = nb._others(None, {"r550"}, now=5.2)
    assert np.isin([550 + 1j], z).sum() == 0 and z.size == 100
