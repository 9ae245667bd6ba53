"""mujoco_ros2_control's site-velocity launch test (tests/upstream/mujoco_ros2_control_tests/test/
site_velocity_launch_test.py), translated: its slider robot, with its files unchanged, run by
`batchsim` in a subprocess over real DDS, and every assertion of that test checked with rclpy.
Domain 92 is this file's base (domain_id takes the next free one up when a concurrent run holds it).

The robot is one prismatic joint driven by a MuJoCo <velocity> actuator on a *site*
(site_velocity_robot.xml: `<velocity name="slider_joint" site="drive_site"/>`), not on the
joint: the command interface slider_joint/velocity must still reach it, by the actuator's name.
The launch file (site_velocity_test_launch.py: xacro site_velocity_robot.urdf headless:=true,
ros2_control_node with site_velocity_controllers.yaml, spawners for joint_state_broadcaster and
site_velocity_controller) becomes `batchsim --ros2-control site_velocity_robot.urdf
--controllers site_velocity_controllers.yaml` (the model is the URDF's `mujoco_model` param),
one world in the root namespace, so the names are upstream's exactly.

`test_node_start` (check_node_running(robot_state_publisher)) cannot be translated word for
word: batchsim runs no robot_state_publisher node but publishes what it would, the latched
/robot_description, itself; that is checked instead.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from ros_fleet import Fleet, domain_id

pytestmark = pytest.mark.ros

TESTS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_tests"
UPSTREAM = [
    "--ros2-control", f"{TESTS / 'test_resources' / 'robot' / 'site_velocity_robot.urdf'} headless:=true",
    "--controllers", str(TESTS / "config" / "site_velocity_controllers.yaml"),
    "--backend", "cpu",
]  # fmt: skip
CONTROLLERS = ["joint_state_broadcaster", "site_velocity_controller"]

# Upstream waits 2 s of wall time for the slider to pass start + 0.5 m at a 0.5 m/s command. The
# physics leaves little slack: the site actuator (kv 1) against the joint's damping 0.2 and 1 kg
# settles at 0.5/1.2 = 0.417 m/s with a 0.83 s time constant, so it takes 1.96 s of simulated
# time to cover 0.5 m. batchsim runs at real-time factor 1 only as far as the machine allows, and
# on the 2-core CI machine (shared with other tests) DDS latency and a slower-than-real-time
# stretch easily eat the remaining 40 ms. So the wall-clock windows are looser here (MOVE_WALL_S,
# VELOCITY_WALL_S), and upstream's 2 s is checked where it cannot depend on the machine's load:
# in simulated time, from the stamps of /joint_states (see test_site_velocity_actuator_moves_slider).
MOVE_WALL_S = 10.0
VELOCITY_WALL_S = 10.0


@pytest.fixture(scope="module")
def ros():
    """The message modules, imported here: a missing package fails these tests, never skips them."""
    import controller_manager_msgs.srv as cm
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray, String

    return dict(cm=cm, Clock=Clock, JointState=JointState, Float64MultiArray=Float64MultiArray, String=String)


@pytest.fixture(scope="module")
def robot(tmp_path_factory, ros):
    """site_velocity_test_launch.py with headless:=true, started once for the whole module."""
    log = tmp_path_factory.mktemp("site_velocity") / "batchsim.log"
    with Fleet(domain_id(92), ["--worlds", "1", "--namespace", "", *UPSTREAM], log) as fleet:
        fleet.js = fleet.latest(ros["JointState"], "/joint_states", keep=2000)
        fleet.actuators = fleet.latest(ros["JointState"], "/mujoco_actuators_states")
        fleet.wait(lambda: fleet.js.count > 0, 40, "/joint_states")
        yield fleet


def _value(msg, field, joint="slider_joint"):
    """get_joint_value: the joint's `field` in a JointState, None if absent."""
    if msg is None or joint not in msg.name:
        return None
    return getattr(msg, field)[list(msg.name).index(joint)]


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def test_node_start(robot, ros):
    """check_node_running(robot_state_publisher): batchsim has no such node; what that node
    serves, the latched robot_description of the xacro'd URDF, is checked in its place."""
    from rclpy.qos import DurabilityPolicy, QoSProfile

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    description = robot.latest(ros["String"], "/robot_description", qos=latched)
    robot.wait(lambda: description.count > 0, 20, "/robot_description")
    assert 'name="site_velocity_robot"' in description.msg.data
    assert 'name="slider_joint"' in description.msg.data and "$(arg" not in description.msg.data


def test_clock(robot, ros):
    """WaitForTopics([("/clock", Clock)], timeout=10.0)."""
    clock = robot.latest(ros["Clock"], "/clock")
    robot.wait(lambda: clock.count > 0, 10, "/clock")


@pytest.mark.parametrize("topic", ["/joint_states", "/mujoco_actuators_states"])
def test_joint_and_actuator_states_published(robot, ros, topic):
    """check_if_js_published(topic, ["slider_joint"]): a message within 20 s naming exactly
    slider_joint (as many names as joints, the same set)."""
    sink = robot.latest(ros["JointState"], topic)  # a fresh subscription, as WaitForTopics makes
    robot.wait(lambda: sink.count > 0, 20, topic)
    msg = sink.msg
    assert len(msg.name) == 1, f"Wrong number of joints in message: {list(msg.name)}"
    assert set(msg.name) == {"slider_joint"}, f"Wrong joint names: {list(msg.name)}"


def test_available_hardware_interfaces(robot, ros):
    reply = robot.call(
        ros["cm"].ListHardwareInterfaces, "/controller_manager/list_hardware_interfaces",
        ros["cm"].ListHardwareInterfaces.Request(), timeout=10.0,
    )  # fmt: skip
    assert reply is not None
    state = {i.name for i in reply.state_interfaces}
    command = {i.name for i in reply.command_interfaces}
    assert state == {"slider_joint/position", "slider_joint/velocity", "slider_joint/effort"}
    assert command == {"slider_joint/velocity"}


def _check_controllers_running(fleet, ros, names, timeout=10.0):
    """controller_manager.test_utils.check_controllers_running: each named controller listed
    `active` by /controller_manager/list_controllers within 10 s."""

    def active():
        reply = fleet.call(
            ros["cm"].ListControllers,
            "/controller_manager/list_controllers",
            ros["cm"].ListControllers.Request(),
        )
        assert reply.controller, "No controllers found!"
        return {c.name for c in reply.controller if c.state == "active"} >= set(names)

    fleet.wait(active, timeout, f"controllers {names} active")


def test_site_velocity_actuator_moves_slider(robot, ros):
    _check_controllers_running(robot, ros, CONTROLLERS)

    pub = robot.node.create_publisher(ros["Float64MultiArray"], "/site_velocity_controller/commands", 10)
    robot.wait(lambda: pub.get_subscription_count() > 0, 5.0, "the controller subscribed to its commands")

    robot.wait(lambda: _value(robot.js.msg, "position") is not None, 15, "a slider joint state")
    start = robot.js.msg
    start_position = _value(start, "position")

    pub.publish(ros["Float64MultiArray"](data=[0.5]))  # once, as upstream: the controller holds it
    sent = time.monotonic()

    def moved():
        position = _value(robot.js.msg, "position")
        return position is not None and position > start_position + 0.5

    robot.wait(moved, MOVE_WALL_S, "the slider past start + 0.5 (slider joint did not move sufficiently)")
    took_wall = time.monotonic() - sent
    # upstream's 2 s, in simulated time (the stamps of /joint_states, sampled at the broadcaster's
    # 50 Hz): from the last sample before the slider moved (the command took effect after it) to
    # the first one past start + 0.5, which lags the crossing by up to one 20 ms period. The
    # physics gives 1.96 s from the command's first step, so this holds at any machine load.
    history = [m for m in robot.js.history if _stamp(m) >= _stamp(start)]
    still = [m for m in history if abs(_value(m, "position") - start_position) < 1e-9]
    past = next(m for m in history if _value(m, "position") > start_position + 0.5)
    took_sim = _stamp(past) - _stamp(still[-1])
    assert took_sim <= 2.0 + 0.02 + 1e-6, (
        f"{took_sim:.3f} s of sim time to move 0.5 m (wall {took_wall:.2f} s)"
    )

    def fast():
        velocity = _value(robot.actuators.msg, "velocity")
        return velocity is not None and velocity > 0.4

    robot.wait(fast, VELOCITY_WALL_S, "an actuator state with slider velocity > 0.4")
    # and upstream's second 2 s window, in simulated time likewise (0.417 m/s is near: ~0.7 s on)
    assert _stamp(robot.actuators.msg) - _stamp(past) <= 2.0, (
        "slider velocity > 0.4 came too late in sim time"
    )
