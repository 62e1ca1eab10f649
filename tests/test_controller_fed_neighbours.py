"""A controller that drives every robot feeds the fleet filter its own decoded poses (one pose
subscription, not two); a shard's filter subscribes to every pose itself."""

from __future__ import annotations

import time

from confnav.schemas import Pose, encode
from confnav.services.bus import InMemoryNetwork
from confnav.services.shard import RobotSelector
from test_services_controller import K, setup, wait_for


def _pose_subs(net: InMemoryNetwork) -> int:
    with net.lock:
        return sum(1 for e, _ in net.subs if e.endswith("/pose"))


def test_fed_filter_sees_every_valid_pose_and_no_malformed_one(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net)
    try:
        nb = ctl.neighbours
        assert nb is not None and nb.fed
        assert _pose_subs(mem_net) == 1  # the controller's only
        cl.goal("a")
        cl.pose("a", 0.3, 0.2)  # with a goal
        cl.pose("b", -0.4, 0.1)  # no goal: still a neighbour of the others
        wait_for(lambda: {"a", "b"} <= set(nb._seen))
        assert nb._seen["a"].z == complex(0.3, 0.2) and nb._seen["b"].z == complex(-0.4, 0.1)
        bad = [  # one robot each (of several waiting poses of one robot only the newest is read)
            b'{"robot_id":"c0","stamp_ns":1,"x":NaN,"y":0.0}',
            b'{"robot_id":"c1","stamp_ns":1,"x":"0.1","y":0.0}',
            b'{"robot_id":"c2","stamp_ns":1,"x":0.1}',
            b'{"robot_id":"c3","stamp_ns":1,"x":0.1,"y":0.0,"extra":1}',
            encode(Pose(robot_id="d", stamp_ns=1, x=0.1, y=0.1)),  # on c4: names another robot
        ]
        n0 = ctl.counters["rejected"]
        for i, payload in enumerate(bad):
            cl.bus.publish(K.robot(f"c{i}", "pose"), payload)
        wait_for(lambda: ctl.counters["rejected"] - n0 >= len(bad))
        cl.pose("a", 0.31, 0.2)  # and the service carries on
        wait_for(lambda: nb._seen["a"].z == complex(0.31, 0.2))
        assert not {"c0", "c1", "c2", "c3", "c4", "d"} & set(nb._seen)
    finally:
        ctl.stop()


def test_a_shard_filter_subscribes_to_every_pose(mem_net: InMemoryNetwork) -> None:
    ctl, _tr, cl = setup(mem_net, robots=RobotSelector.parse("a"))
    try:
        nb = ctl.neighbours
        assert nb is not None and not nb.fed
        assert _pose_subs(mem_net) == 2  # the shard's robots, and every robot for the filter
        cl.bus.publish(K.robot("z", "pose"), encode(Pose(robot_id="z", stamp_ns=time.time_ns(),
                                                         seq=1, x=0.2, y=0.2)))  # fmt: skip
        wait_for(lambda: "z" in nb._seen)  # a robot of another shard
    finally:
        ctl.stop()
