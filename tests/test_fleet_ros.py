"""A world of several robots over real DDS (batchsim.fleet): every robot of every world on its
own namespace `/<world>/<robot>/`, with its own joint_states, controller_manager, actions and
robot_description, in one tf tree per world. Domains 100-101 belong to this file.

One fleet of 4 worlds, each holding two arms (`arm_a`, `arm_b`) and a rover, serves the checks
that follow in file order.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import need

rclpy = need("rclpy")  # skips where ROS is absent, fails instead under BATCHSIM_FORCE_BACKENDS=1

import yaml  # noqa: E402
from ros_fleet import Fleet, domain_id, stack_messages  # noqa: E402

pytestmark = pytest.mark.ros

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
JTC = "joint_trajectory_controller"
ROBOTS = ("arm_a", "arm_b", "rover")


@pytest.fixture(scope="module")
def ros():
    return stack_messages()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, ros):
    root = tmp_path_factory.mktemp("fleet")
    path = root / "two_arms_and_a_rover.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "robots": [
                    {"name": "arm_a", "model": "arm", "pose": [0.0, 0.0, 0.0, 0.0]},
                    {"name": "arm_b", "model": "arm", "pose": [1.5, 0.0, 0.0, 3.14159265]},
                    {"name": "rover", "model": "rover", "pose": [0.0, 2.0, 0.0, 0.0]},
                ]
            }
        )
    )
    # each robot's default controllers (the helper's `--controllers none` comes first)
    args = ["--fleet", str(path), "--worlds", "4", "--backend", "cpu", "--bridge-workers", "2", "--controllers", "default"]
    with Fleet(domain_id(100), args, root / "batchsim.log") as f:
        f.js = {(w, r): f.latest(ros["JointState"], f"/world_{w}/{r}/joint_states") for w in range(4) for r in ROBOTS}
        f.wait(lambda: all(s.count > 0 for s in f.js.values()), 40, "every robot's joint_states")
        yield f


def _call(fleet, ros, world: int, robot: str, name: str, request=None):
    srv = {
        "list_controllers": ros["srv"].ListControllers,
        "switch_controller": ros["srv"].SwitchController,
        "list_hardware_components": ros["srv"].ListHardwareComponents,
    }[name]
    return fleet.call(srv, f"/world_{world}/{robot}/controller_manager/{name}", request or srv.Request(), timeout=40)


def _states(fleet, ros, world: int, robot: str) -> dict[str, str]:
    return {c.name: c.state for c in _call(fleet, ros, world, robot, "list_controllers").controller}


def test_each_robot_has_its_own_joint_states_named_as_the_robot_names_them(fleet):
    assert list(fleet.js[(2, "arm_b")].msg.name) == ARM_JOINTS
    assert list(fleet.js[(2, "rover")].msg.name) == ["left_wheel_joint", "right_wheel_joint"]


def test_diagnostics_name_each_worlds_robots(fleet):
    diag = fleet.diagnostics()
    fleet.wait(lambda: diag.world("world_1") is not None, 20, "world 1's diagnostics")
    assert diag.value("world_1", "robots") == "arm_a, arm_b, rover"


def test_each_robot_has_its_own_controller_manager(fleet, ros):
    assert _states(fleet, ros, 3, "arm_b") == {
        "joint_state_broadcaster": "active", JTC: "active", "wrist_ft_broadcaster": "active"
    }
    assert _states(fleet, ros, 3, "rover") == {"joint_state_broadcaster": "active", "diff_drive_controller": "active"}
    components = _call(fleet, ros, 3, "arm_b", "list_hardware_components").component
    assert [c.name for c in components] == ["arm_b"]
    assert [i.name for i in components[0].command_interfaces] == [f"{j}/position" for j in ARM_JOINTS]


def test_a_goal_to_one_robot_moves_only_it(fleet, ros):
    before = {key: np.array(s.msg.position) for key, s in fleet.js.items()}
    client = ros["ActionClient"](fleet.node, ros["FJT"], f"/world_1/arm_a/{JTC}/follow_joint_trajectory")
    assert client.wait_for_server(timeout_sec=40), fleet.log()
    time.sleep(1.0)  # the server matches the client's reader (test_ros_stack.py says why)
    target = [0.4, -0.3, 0.5, 0.2, -0.4, 0.6]
    point = ros["JointTrajectoryPoint"](positions=target, time_from_start=ros["Duration"](sec=1))
    goal = ros["FJT"].Goal(trajectory=ros["JointTrajectory"](joint_names=ARM_JOINTS, points=[point]))
    handle = fleet.send_goal(client, goal)
    assert handle.accepted
    result = handle.get_result_async()
    fleet.wait(result.done, 40, "the goal's result")
    assert result.result().status == 4, result.result()  # SUCCEEDED
    fleet.wait(lambda: np.abs(np.array(fleet.js[(1, "arm_a")].msg.position) - target).max() < 0.05, 10, "arm_a at the target")
    for key, was in before.items():
        if key != (1, "arm_a") and key[1] != "rover":  # the rover rolls a hair on its own
            assert np.abs(np.array(fleet.js[key].msg.position) - was).max() < 1e-3, f"{key} moved"


def test_switching_a_controller_of_one_robot_in_one_world_changes_nothing_else(fleet, ros):
    request = ros["srv"].SwitchController.Request(deactivate_controllers=[JTC], strictness=2)
    answer = _call(fleet, ros, 3, "arm_b", "switch_controller", request)
    assert answer.ok, answer.message
    assert _states(fleet, ros, 3, "arm_b")[JTC] == "inactive"
    assert _states(fleet, ros, 3, "arm_a")[JTC] == "active"  # the other robot of that world
    assert _states(fleet, ros, 2, "arm_b")[JTC] == "active"  # that robot in another world
    # another robot's controller is unknown to this robot's controller_manager
    request = ros["srv"].SwitchController.Request(activate_controllers=["diff_drive_controller"], strictness=2)
    assert not _call(fleet, ros, 3, "arm_b", "switch_controller", request).ok
    request = ros["srv"].SwitchController.Request(activate_controllers=[JTC], strictness=2)
    assert _call(fleet, ros, 3, "arm_b", "switch_controller", request).ok


def test_each_robot_has_a_latched_robot_description_of_its_own_links(fleet, ros):
    import xml.etree.ElementTree as ET

    latched = ros["QoSProfile"](depth=1, durability=ros["DurabilityPolicy"].TRANSIENT_LOCAL)
    arm = fleet.latest(ros["String"], "/world_0/arm_b/robot_description", qos=latched)
    rover = fleet.latest(ros["String"], "/world_0/rover/robot_description", qos=latched)
    fleet.wait(lambda: arm.msg is not None and rover.msg is not None, 30, "the robots' descriptions")
    links = {link.get("name") for link in ET.fromstring(arm.msg.data).iter("link")}
    assert {"link1", "link6"} <= links and not any("/" in name for name in links)
    assert "left_wheel" in {link.get("name") for link in ET.fromstring(rover.msg.data).iter("link")}


def test_every_robot_of_a_world_is_in_its_one_tf_tree_and_odom_names_frames_in_it(fleet, ros):
    latched = ros["QoSProfile"](depth=100, durability=ros["DurabilityPolicy"].TRANSIENT_LOCAL)
    tf = fleet.latest(ros["TFMessage"], "/world_2/tf")
    static = fleet.latest(ros["TFMessage"], "/world_2/tf_static", qos=latched)
    odom = fleet.latest(ros["Odometry"], "/world_2/rover/odom")
    wheel = fleet.latest(ros["Odometry"], "/world_2/rover/diff_drive_controller/odom")  # the wheels' odometry
    fleet.wait(lambda: tf.msg is not None and odom.msg is not None and wheel.msg is not None, 30, "tf and odom")
    time.sleep(0.5)
    parent = {t.child_frame_id: t.header.frame_id for t in tf.msg.transforms}
    if static.msg is not None:
        parent.update({t.child_frame_id: t.header.frame_id for t in static.msg.transforms})

    def ancestors(frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in parent and len(chain) < 100:
            chain.append(parent[chain[-1]])
        return chain

    # every robot's frames hang from the world's root, which hangs from the fleet's `world`
    for frame in ("world_2/arm_a/link6", "world_2/arm_b/link6", "world_2/rover/left_wheel", "world_2/rover/base"):
        assert ancestors(frame)[-2:] == ["world_2/world", "world"], (frame, ancestors(frame))
    assert "world_2/world" in ancestors(odom.msg.child_frame_id)
    assert odom.msg.header.frame_id == "world_2/world"
    # the diff drive's frames: its odom -> base_link on tf (enable_odom_tf), its odom where the
    # rover started (tf_static); every frame id a robot's messages name is in the world's tree
    assert (wheel.msg.header.frame_id, wheel.msg.child_frame_id) == ("world_2/rover/odom", "world_2/rover/base_link")
    assert ancestors("world_2/rover/base_link")[-3:] == ["world_2/rover/odom", "world_2/world", "world"]
    assert abs(odom.msg.pose.pose.position.y - 2.0) < 0.05  # the rover stands where the fleet file put it


# ---------------------------------------------------------------- each robot commanded and reset alone

WHEELS = 2  # a rover's command interfaces: its two wheels' efforts


@pytest.fixture(scope="module")
def duel(tmp_path_factory, ros):
    """2 worlds, no controllers: two rovers facing each other 1.2 m apart, and an arm to the side."""
    import math

    root = tmp_path_factory.mktemp("duel")
    path = root / "duel.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "robots": [
                    {"name": "left", "model": "rover", "pose": [0.0, 0.0, 0.0, 0.0]},
                    {"name": "right", "model": "rover", "pose": [1.2, 0.0, 0.0, math.pi]},
                    {"name": "arm", "model": "arm", "pose": [0.0, 3.0, 0.0, 0.0]},
                ]
            }
        )
    )
    with Fleet(domain_id(101), ["--fleet", str(path), "--worlds", "2", "--backend", "cpu"], root / "batchsim.log") as f:
        f.js = {(w, r): f.latest(ros["JointState"], f"/world_{w}/{r}/joint_states") for w in range(2) for r in ("arm", "left")}
        f.odom = {(w, r): f.latest(ros["Odometry"], f"/world_{w}/{r}/odom") for w in range(2) for r in ("left", "right")}
        f.wait(lambda: all(s.count > 0 for s in [*f.js.values(), *f.odom.values()]), 40, "joint_states and odom")
        yield f


def _x(duel, world: int, robot: str) -> float:
    return duel.odom[(world, robot)].msg.pose.pose.position.x


def test_two_robots_driven_into_each_other_over_ros_stop_pressed_together(duel):
    """World 0's rovers driven at each other through their own command vectors
    (`<ns>/<robot>/commands`): they meet and stop 0.3-0.6 m apart (2 m of driving would cross
    them), pushing with their wheels' effort: the contact between two robots holds them."""
    from std_msgs.msg import Float64MultiArray

    push = Float64MultiArray(data=[0.5] * WHEELS)

    def stopped() -> bool:
        gap = _x(duel, 0, "right") - _x(duel, 0, "left")
        speed = abs(duel.odom[(0, "left")].msg.twist.twist.linear.x)
        return 0.3 < gap < 0.6 and speed < 0.01

    deadline = time.monotonic() + 30
    while not stopped():
        for robot in ("left", "right"):
            duel.publish(Float64MultiArray, f"/world_0/{robot}/commands", push)
        assert time.monotonic() < deadline, (_x(duel, 0, "left"), _x(duel, 0, "right"))
        time.sleep(0.05)
    for _ in range(20):  # still pushing, still stopped, still apart
        for robot in ("left", "right"):
            duel.publish(Float64MultiArray, f"/world_0/{robot}/commands", push)
        time.sleep(0.05)
    assert stopped()
    efforts = duel.js[(0, "left")].msg.effort
    assert min(efforts) > 0.1, efforts  # the wheels push; the other robot holds them
    assert abs(_x(duel, 1, "left")) < 0.05  # world 1's rovers never moved


def test_a_robots_own_command_vector_and_reset_touch_only_it(duel):
    """/world_1/arm/commands moves world 1's arm only; /world_1/arm/reset puts it back home while
    world 1's rover, driven meanwhile, stays where it went, and world 0's arm never moved."""
    from std_msgs.msg import Float64MultiArray
    from std_srvs.srv import Trigger

    def joint1(w: int) -> float:
        return duel.js[(w, "arm")].msg.position[0]

    away = Float64MultiArray(data=[0.8, 0.0, 0.0, 0.0, 0.0, 0.0])  # the arm's six positions, in its own order
    duel.publish_until(Float64MultiArray, "/world_1/arm/commands", away, lambda: joint1(1) > 0.6, 30, "world 1's arm away")
    start = _x(duel, 1, "left")
    drive = Float64MultiArray(data=[0.3] * WHEELS)
    duel.publish_until(Float64MultiArray, "/world_1/left/commands", drive, lambda: _x(duel, 1, "left") > start + 0.05, 30)
    duel.publish(Float64MultiArray, "/world_1/left/commands", Float64MultiArray(data=[0.0] * WHEELS))
    assert abs(joint1(0)) < 0.05  # world 0's arm: not commanded
    answer = duel.call(Trigger, "/world_1/arm/reset", Trigger.Request())
    assert answer.success and answer.message == "reset robot arm", answer.message
    duel.wait(lambda: abs(joint1(1)) < 0.05, 20, "world 1's arm back home")
    assert _x(duel, 1, "left") > start + 0.04  # the rover beside it was not reset
    assert "batchsim: error" not in duel.log()
