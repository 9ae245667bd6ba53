"""A fleet of two groups of worlds over real DDS (batchsim.fleet.groups): each group its own
robots, numbered as one fleet, one /clock, the fleet's services acting on every group.

One fleet of 2 worlds of an arm (group `arms`) and 2 worlds of a rover beside an arm (group
`yard`, worlds 2 and 3) serves the checks that follow in file order.
"""

from __future__ import annotations

import time

import pytest
from conftest import need
from depot import DEPOT

rclpy = need("rclpy")  # skips where ROS is absent, fails instead under BATCHSIM_FORCE_BACKENDS=1

import yaml  # noqa: E402
from ros_fleet import Fleet, domain_id  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState

    root = tmp_path_factory.mktemp("groups")
    path = root / "depot.yaml"
    path.write_text(yaml.safe_dump(DEPOT))
    with Fleet(domain_id(60), ["--fleet", str(path), "--backend", "cpu", "--bridge-workers", "1"], root / "batchsim.log") as f:
        f.clock = f.latest(Clock, "/clock")
        f.js = {
            (w, r): f.latest(JointState, f"/world_{w}/{r}/joint_states")
            for w, r in [(0, "arm"), (1, "arm"), (2, "arm"), (2, "rover"), (3, "arm"), (3, "rover")]
        }
        f.wait(lambda: f.clock.count > 0 and all(s.count > 0 for s in f.js.values()), 60, "every group's joint_states and /clock")
        yield f


def test_every_group_is_numbered_and_namespaced_as_one_fleet(fleet):
    assert list(fleet.js[(2, "rover")].msg.name) == ["left_wheel_joint", "right_wheel_joint"]
    assert len(fleet.js[(0, "arm")].msg.name) == 6
    assert fleet.node.count_publishers("/world_4/arm/joint_states") == 0  # no fifth world


def test_a_fleet_of_two_groups_is_one_clock(fleet):
    assert fleet.node.count_publishers("/clock") == 1
    assert fleet.node.count_publishers("/world_0/arm/joint_states") == 1
    assert fleet.node.count_publishers("/world_3/rover/joint_states") == 1


def test_pause_stops_every_group_and_a_step_steps_them_all(fleet):
    from std_srvs.srv import SetBool, Trigger

    watched = [(0, "arm"), (3, "rover")]  # one world of each group

    def stamps():
        return {k: (fleet.js[k].msg.header.stamp.sec, fleet.js[k].msg.header.stamp.nanosec) for k in watched}

    assert fleet.call(SetBool, "/batchsim/pause", SetBool.Request(data=True)).success
    time.sleep(1.0)  # what was published before the pause has arrived
    paused = stamps()
    time.sleep(1.0)
    assert stamps() == paused  # no group ran on
    answer = fleet.call(Trigger, "/batchsim/step", Trigger.Request())
    assert answer.success, answer.message
    fleet.wait(lambda: all(stamps()[k] > paused[k] for k in watched), 20, "one period in both groups")
    assert fleet.call(SetBool, "/batchsim/pause", SetBool.Request(data=False)).success


def test_a_worlds_reset_in_the_second_group_resets_that_world_only(fleet):
    """World 3 (group yard's second world) and world 2 beside it driven away from home; /world_3/reset
    puts world 3's arm back, world 2's stays where it was driven."""
    from std_msgs.msg import Float64MultiArray
    from std_srvs.srv import Trigger

    def joint1(w: int) -> float:
        return fleet.js[(w, "arm")].msg.position[0]

    away = Float64MultiArray(data=[0.8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # the arm's 6 positions, the rover's 2 efforts
    for w in (2, 3):
        fleet.publish_until(Float64MultiArray, f"/world_{w}/commands", away, lambda w=w: joint1(w) > 0.6, 30, f"world {w}'s arm away")
    answer = fleet.call(Trigger, "/world_3/reset", Trigger.Request())
    assert answer.success, answer.message
    fleet.wait(lambda: abs(joint1(3)) < 0.1, 20, "world 3's arm back at home")
    assert joint1(2) > 0.6  # its neighbour in the group stays where it was driven
    assert "batchsim: error" not in fleet.log()
