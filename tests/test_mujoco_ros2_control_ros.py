"""mujoco_ros2_control's own launch tests (tests/upstream/mujoco_ros2_control_tests/test/
robot_launch_test.py), translated: its demo robot, with its files unchanged, run by
`batchsim` in a subprocess over real DDS, and every assertion of that test checked with rclpy.
Domains 84-89 belong to this file.

The launch file becomes `batchsim --ros2-control test_robot.urdf --controllers controllers.yaml
--sensors mujoco_ros2_control_plugins.yaml` (the model is the URDF's `mujoco_model` param).
One world in the root namespace gives upstream's exact names (`/joint_states`,
`/mujoco_ros2_control_node/...`); a second fleet of two worlds checks the same under
`/world_1/...`. `check_node_running(robot_state_publisher)`: batchsim's node of that name
publishes the user's URDF on `/robot_description`. What is not translated: the exact settled pose of
`test_pose_interfaces_transform` (its figures are per libmujoco build; here the pose is
checked against MuJoCo's own site pose).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from ros_fleet import Fleet, check_controllers_running, domain_id

pytestmark = pytest.mark.ros

DEMOS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos"
UPSTREAM = [
    "--ros2-control", str(DEMOS / "demo_resources" / "robot" / "test_robot.urdf"),
    "--controllers", str(DEMOS / "config" / "controllers.yaml"),
    "--sensors", str(DEMOS / "config" / "mujoco_ros2_control_plugins.yaml"),
    "--backend", "cpu", "--camera-resolution", "64x48",
]  # fmt: skip
CONTROLLERS = ["gripper_controller", "position_controller", "joint_state_broadcaster"]
NODE = "/mujoco_ros2_control_node"


@pytest.fixture(scope="module")
def ros():
    """The message modules, imported here: a missing package fails these tests, never skips them."""
    import controller_manager_msgs.srv as cm
    import mujoco_ros2_control_msgs.msg as mm
    import mujoco_ros2_control_msgs.srv as ms
    from geometry_msgs.msg import PoseStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, Image, JointState
    from std_msgs.msg import Float64MultiArray

    return dict(
        cm=cm, mm=mm, ms=ms, PoseStamped=PoseStamped, Clock=Clock, CameraInfo=CameraInfo, Image=Image,
        JointState=JointState, Float64MultiArray=Float64MultiArray,
    )  # fmt: skip


@pytest.fixture(scope="module", params=["position", "pid", "transmission", "transmission_pid"])
def robot(request, tmp_path_factory, ros):
    """The demo robot as robot_launch_test.py runs it (use_pid:=false), as
    robot_launch_pid_test.py does (use_pid:=true: motors under mujoco_pid.yaml's PIDs), and as
    robot_launch_transmission(_pid)_test.py do (use_transmissions:=true: joint1/joint2 through a
    differential onto MJCF joints renamed actuator1/actuator2, as 04_transmissions.launch.py)."""
    from test_mujoco_ros2_control import transmission_robot

    folder = tmp_path_factory.mktemp("mrc")
    args = [*UPSTREAM]
    if request.param.endswith("pid"):
        args[1] += " use_pid:=true"
    if request.param.startswith("transmission"):
        args[1] = str(transmission_robot(folder, use_pid=request.param.endswith("pid")))
    with Fleet(domain_id(84), ["--worlds", "1", "--namespace", "", *args], folder / "batchsim.log") as fleet:
        fleet.source = args[1]  # the --ros2-control description, xacro arguments after the path
        fleet.pid = request.param.endswith("pid")
        fleet.transmission = request.param.startswith("transmission")
        fleet.js = fleet.latest(ros["JointState"], "/joint_states")
        fleet.actuators = fleet.latest(ros["JointState"], "/mujoco_actuators_states")
        fleet.pose = fleet.latest(ros["PoseStamped"], "/pose_broadcaster/pose")
        fleet.wait(lambda: fleet.js.count > 0, 40, "/joint_states")
        yield fleet


def _positions(msg, names):
    return {n: msg.position[list(msg.name).index(n)] for n in names} if msg is not None else {}


def _near(sink, expected, delta):
    got = _positions(sink.msg, expected)
    return bool(got) and all(abs(got[n] - v) <= delta for n, v in expected.items())


def _controllers_running(fleet, ros, base=""):
    """upstream's check_controllers_running(node, CONTROLLERS, namespace), as its tests call it:
    the controllers' nodes in the manager's namespace, then each active in list_controllers."""
    check_controllers_running(fleet, CONTROLLERS, base)


def _command(fleet, ros, topic, data, expected, sink, delta=0.05, timeout=15.0):
    msg = ros["Float64MultiArray"](data=[float(v) for v in data])
    fleet.publish_until(ros["Float64MultiArray"], topic, msg, lambda: _near(sink, expected, delta), timeout, topic)


def test_clock_and_joint_states(robot, ros):
    clock = robot.latest(ros["Clock"], "/clock")
    robot.wait(lambda: clock.count > 0, 10, "/clock")
    names = ["joint1", "joint2", "gripper_left_finger_joint", "gripper_right_finger_joint"]
    assert set(names) <= set(robot.js.msg.name)


def test_mujoco_actuators_states_published(robot):
    robot.wait(lambda: robot.actuators.count > 0, 20, "/mujoco_actuators_states")
    arm = ["actuator1", "actuator2"] if robot.transmission else ["joint1", "joint2"]  # the MuJoCo side
    assert list(robot.actuators.msg.name) == [*arm, "gripper_left_finger_joint", "gripper_right_finger_joint"]


def test_available_hardware_interfaces(robot, ros):
    reply = robot.call(
        ros["cm"].ListHardwareInterfaces, "/controller_manager/list_hardware_interfaces", ros["cm"].ListHardwareInterfaces.Request()
    )
    state = [i.name for i in reply.state_interfaces]
    expected_state = [
        *(f"gripper_{side}_finger_joint/{k}" for side in ("left", "right") for k in ("position", "velocity", "effort", "force")),
        *(f"joint{j}/{k}" for j in (1, 2) for k in ("position", "velocity", "effort", "torque")),
        *(f"pose/orientation.{c}" for c in "wxyz"), *(f"pose/position.{c}" for c in "xyz"),
        *(f"magnetometer/magnetic_field.{c}" for c in "xyz"),
    ]  # fmt: skip
    assert len(state) == len(expected_state) and set(state) == set(expected_state), state
    command = [i.name for i in reply.command_interfaces]
    expected = ["joint1/position", "joint2/position", "gripper_left_finger_joint/position"]
    if robot.pid:  # robot_launch_pid_test.py: the PIDs serve velocity too
        expected += ["joint1/velocity", "joint2/velocity"]
    assert sorted(command) == sorted(expected)


def test_pose_interfaces_transform(robot):
    robot.wait(lambda: robot.pose.count > 0, 20, "/pose_broadcaster/pose")
    msg = robot.pose.msg
    assert msg.header.frame_id == "ee_link"
    p, q = msg.pose.position, msg.pose.orientation
    assert np.isfinite([p.x, p.y, p.z, q.w, q.x, q.y, q.z]).all()
    assert abs(np.linalg.norm([q.w, q.x, q.y, q.z]) - 1.0) < 1e-6 and abs(p.y) < 1e-6  # the arm moves in x-z


def test_arm(robot, ros):
    _controllers_running(robot, ros)
    _command(robot, ros, "/position_controller/commands", [0.5, -0.5], {"joint1": 0.5, "joint2": -0.5}, robot.js)
    assert any(abs(e) > 1e-6 for e in robot.js.msg.effort), "Effort field is zero"
    expected = {"joint1": 0.5, "joint2": -0.5}
    if robot.transmission:  # the differential (joint reductions 2.0/0.5): sum and difference
        expected = {"actuator1": 0.5 * 2.0 + -0.5 * 0.5, "actuator2": 0.5 * 2.0 - -0.5 * 0.5}
    robot.wait(lambda: _near(robot.actuators, expected, 0.05), 15, "actuator states at the target")
    assert any(abs(e) > 1e-6 for e in robot.actuators.msg.effort)


def test_gripper(robot, ros):
    _controllers_running(robot, ros)
    target = {"gripper_left_finger_joint": -0.04, "gripper_right_finger_joint": 0.04}
    _command(robot, ros, "/gripper_controller/commands", [-0.04], target, robot.js, delta=0.005)
    robot.wait(lambda: _near(robot.actuators, target, 0.005), 15, "actuator states of the gripper")


def test_camera_topics(robot, ros):
    sinks = {
        "/camera/color/image_raw": robot.latest(ros["Image"], "/camera/color/image_raw"),
        "/camera/color/camera_info": robot.latest(ros["CameraInfo"], "/camera/color/camera_info"),
        "/camera/aligned_depth_to_color/image_raw": robot.latest(ros["Image"], "/camera/aligned_depth_to_color/image_raw"),
    }
    robot.wait(lambda: all(s.count > 0 for s in sinks.values()), 30, "every camera topic")
    assert sinks["/camera/color/image_raw"].msg.header.frame_id == "camera_color_optical_frame"  # the plugin YAML's


def _switch(fleet, ros, activate=(), deactivate=(), base=""):
    request = ros["cm"].SwitchController.Request(
        activate_controllers=list(activate), deactivate_controllers=list(deactivate),
        strictness=ros["cm"].SwitchController.Request.BEST_EFFORT,
    )  # fmt: skip
    assert fleet.call(ros["cm"].SwitchController, f"{base}/controller_manager/switch_controller", request).ok


def test_reset_world_service(robot, ros):
    _controllers_running(robot, ros)
    _command(robot, ros, "/position_controller/commands", [-0.5, 0.5], {"joint1": -0.5, "joint2": 0.5}, robot.js, 0.075)
    _switch(robot, ros, deactivate=["position_controller"])
    reply = robot.call(ros["ms"].ResetWorld, f"{NODE}/reset_world", ros["ms"].ResetWorld.Request())
    assert reply.success, reply.message
    assert reply.message == "Successfully reset the MuJoCo world to the initial state."
    time.sleep(1.0)
    robot.wait(lambda: _near(robot.js, {"joint1": 0.0, "joint2": 0.0}, 0.05), 15, "the joints back at zero")
    _switch(robot, ros, activate=["position_controller"])
    _command(robot, ros, "/position_controller/commands", [-0.5, 0.5], {"joint1": -0.5, "joint2": 0.5}, robot.js, 0.075)


def _pause(fleet, ros, paused: bool):
    reply = fleet.call(ros["ms"].SetPause, f"{NODE}/set_pause", ros["ms"].SetPause.Request(paused=paused))
    assert reply.success, reply.message
    return reply


def test_step_simulation_zero_steps_rejected(robot, ros):
    _pause(robot, ros, True)
    try:
        reply = robot.call(ros["ms"].StepSimulation, f"{NODE}/step_simulation", ros["ms"].StepSimulation.Request(steps=0))
        assert not reply.success and reply.message == "Number of steps must be positive, got: 0"
    finally:
        _pause(robot, ros, False)


def test_step_simulation_steps_exactly_n_physics_steps(robot, ros):
    clock = robot.latest(ros["Clock"], "/clock")
    assert "already running" in _pause(robot, ros, False).message
    _pause(robot, ros, True)
    try:
        robot.wait(lambda: clock.count > 0, 10, "/clock")
        # the clock of the period that ran as the pause came may still be on its way: read it still
        seen = [-1.0]

        def still() -> bool:
            now = clock.msg.clock.sec + clock.msg.clock.nanosec * 1e-9
            same, seen[0] = now == seen[0], now
            time.sleep(0.2)
            return same

        robot.wait(still, 10, "/clock to stand still while paused")
        before = seen[0]
        reply = robot.call(ros["ms"].StepSimulation, f"{NODE}/step_simulation", ros["ms"].StepSimulation.Request(steps=7))
        assert reply.success and reply.message == "Completed 7 simulation step(s).", reply.message
        # 7 steps of 2 ms: a whole 10 ms control period and a shorter one of 4 ms
        robot.wait(lambda: abs(clock.msg.clock.sec + clock.msg.clock.nanosec * 1e-9 - before - 0.014) < 1e-9, 5, "/clock 14 ms on")
    finally:
        _pause(robot, ros, False)


def test_step_simulation_refused_while_running(robot, ros):
    reply = robot.call(ros["ms"].StepSimulation, f"{NODE}/step_simulation", ros["ms"].StepSimulation.Request(steps=5))
    assert not reply.success and reply.message == "Cannot step simulation: simulation is not paused."


def test_step_simulation_interrupted_by_resume(robot, ros):
    _pause(robot, ros, True)
    client = robot.node.create_client(ros["ms"].StepSimulation, f"{NODE}/step_simulation")
    try:
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(ros["ms"].StepSimulation.Request(steps=50000))  # 100 s of sim time
        time.sleep(0.2)
        _pause(robot, ros, False)
        robot.wait(future.done, 5, "the step_simulation answer")
        result = future.result()
        assert not result.success and "resumed" in result.message, result.message
    finally:
        robot.node.destroy_client(client)
        _pause(robot, ros, False)


def _free(ros, name, xyz, frame=""):
    entry = ros["mm"].FreeJointState(name=name)
    entry.pose.pose.position.x, entry.pose.pose.position.y, entry.pose.pose.position.z = xyz
    entry.pose.pose.orientation.w = 1.0
    entry.pose.header.frame_id = frame
    return entry


def _default_scene_only(robot):
    if robot.pid or robot.transmission:  # as upstream skips them: not in the PID or transmission scenes
        pytest.skip("cube1/cube2 and the start_90 keyframe are only in the default test_robot.xml scene")


def test_reset_free_body_poses(robot, ros):
    _default_scene_only(robot)
    request = ros["ms"].SetFreeJointState.Request(
        free_joints=[_free(ros, "cube1", (1.0, 1.0, 1.0)), _free(ros, "cube2", (-1.0, 1.0, 1.0))]
    )
    reply = robot.call(ros["ms"].SetFreeJointState, f"{NODE}/set_free_joint_state", request)
    assert reply.success, reply.message


def test_bad_requests_change_nothing(robot, ros):
    _default_scene_only(robot)
    ms = ros["ms"]
    request = ms.SetFreeJointState.Request(free_joints=[_free(ros, "cube1", (0, 0, 1)), _free(ros, "cube9", (0, 0, 1))])
    reply = robot.call(ms.SetFreeJointState, f"{NODE}/set_free_joint_state", request)
    assert not reply.success and reply.message == "Entry 1 ('cube9'): Unknown body name."
    request = ms.SetFreeJointState.Request(free_joints=[_free(ros, "upperarm", (0, 0, 1))])
    assert "Body is not driven by a free joint" in robot.call(ms.SetFreeJointState, f"{NODE}/set_free_joint_state", request).message
    reset = ms.ResetWorld.Request(keyframe="nowhere")
    reply = robot.call(ms.ResetWorld, f"{NODE}/reset_world", reset)
    assert not reply.success and reply.message.startswith("Failed to apply keyframe: 'nowhere'") and "Not resetting" in reply.message
    reset = ms.ResetWorld.Request()
    reset.state_overrides.joint_states.name = ["joint1", "cube1_freejoint"]
    reply = robot.call(ms.ResetWorld, f"{NODE}/reset_world", reset)
    assert not reply.success and "Entry 1 ('cube1_freejoint'): Not a single-DOF (hinge or slide) joint." in reply.message


def test_reset_to_a_keyframe_with_overrides(robot, ros):
    _default_scene_only(robot)
    ms = ros["ms"]
    _switch(robot, ros, deactivate=["position_controller"])
    _pause(robot, ros, True)  # the pose is checked where the reset put it, before gravity moves the arm
    try:
        reset = ms.ResetWorld.Request(keyframe="start_90")
        reset.state_overrides.joint_states.name = ["joint2"]
        reset.state_overrides.joint_states.position = [-1.0]
        reset.state_overrides.free_joints = [_free(ros, "cube1", (0.0, 0.0, 0.5), frame="forearm")]
        reply = robot.call(ms.ResetWorld, f"{NODE}/reset_world", reset)
        assert reply.success, reply.message
        assert reply.message == "Successfully reset the MuJoCo world to the 'start_90' state. Applied 1 joint and 1 free-joint override(s)."
        # the keyframe's joint1 (1.57), joint2 overridden: published at once while paused
        robot.wait(lambda: _near(robot.js, {"joint1": 1.57, "joint2": -1.0}, 1e-3), 10, "the keyframe's pose")
    finally:
        _pause(robot, ros, False)
        _switch(robot, ros, activate=["position_controller"])
        robot.call(ms.ResetWorld, f"{NODE}/reset_world", ms.ResetWorld.Request())


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, ros):
    log = tmp_path_factory.mktemp("mrc2") / "batchsim.log"
    with Fleet(domain_id(86), ["--worlds", "2", *UPSTREAM], log) as fleet:
        fleet.js = [fleet.latest(ros["JointState"], f"/world_{w}/joint_states") for w in range(2)]
        fleet.wait(lambda: all(s.count > 0 for s in fleet.js), 40, "joint_states")
        yield fleet


def test_a_fleet_serves_each_world_under_its_namespace(fleet, ros):
    _controllers_running(fleet, ros, "/world_1")
    _command(fleet, ros, "/world_1/position_controller/commands", [0.5, -0.5], {"joint1": 0.5, "joint2": -0.5}, fleet.js[1])
    assert _near(fleet.js[0], {"joint1": 0.0, "joint2": 0.0}, 0.05)  # world 0 unmoved
    reply = fleet.call(ros["ms"].ResetWorld, f"/world_1{NODE}/reset_world", ros["ms"].ResetWorld.Request())
    assert reply.success, reply.message
    reply = fleet.call(
        ros["ms"].SetFreeJointState, f"/world_0{NODE}/set_free_joint_state",
        ros["ms"].SetFreeJointState.Request(free_joints=[_free(ros, "cube1", (1.0, 1.0, 1.0))]),
    )  # fmt: skip
    assert reply.success, reply.message
    # the fleet's own: pausing pauses every world (they run in lockstep)
    assert fleet.call(ros["ms"].SetPause, f"{NODE}/set_pause", ros["ms"].SetPause.Request(paused=True)).success
    assert fleet.call(ros["ms"].SetPause, f"{NODE}/set_pause", ros["ms"].SetPause.Request(paused=False)).success


def test_robot_description_is_the_users_urdf_and_its_links_are_in_tf(robot, ros):
    """With the peer's URDF given (--ros2-control), /robot_description is that URDF, published by a
    node named robot_state_publisher (upstream's test_node_start checks it runs), and every link
    of it is a frame of the tf tree under `world` (its fixed links are the MJCF's sites). Before:
    a URDF generated from the MJCF (robot `scene`, no `base`, `ee_link`, camera or lidar links)."""
    import xml.etree.ElementTree as ET

    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String
    from tf2_msgs.msg import TFMessage

    from batchsim.model.description import read_source

    latched = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    description = robot.latest(String, "/robot_description", qos=latched)
    robot.wait(lambda: description.count > 0, 20, "/robot_description")
    urdf = ET.fromstring(description.msg.data)
    assert urdf.get("name") == "two_dof_robot"
    assert description.msg.data == read_source(robot.source)[0]  # xacro expanded
    assert "robot_state_publisher" in robot.node.get_node_names()
    assert robot.node.count_publishers("/robot_description") == 1
    parents: dict[str, str] = {}

    def on_tf(msg) -> None:
        parents.update({t.child_frame_id: t.header.frame_id for t in msg.transforms})

    robot.node.create_subscription(TFMessage, "/tf_static", on_tf, latched)
    robot.node.create_subscription(TFMessage, "/tf", on_tf, 10)
    links = {link.get("name") for link in urdf.iter("link")} - {"world"}

    def root(frame: str) -> str:
        while frame in parents:
            frame = parents[frame]
        return frame

    robot.wait(lambda: all(root(link) == "world" and link in parents for link in links), 20, f"every link of {sorted(links)} in tf")


def test_mjcf_generation_from_the_urdf(tmp_path, ros):
    """robot_launch_mjcf_generation_test.py: the demo robot described only by its URDF (demo 02:
    --m test_inputs.xml, --scene scene_info.xml), its generated MJCF on /mujoco_robot_description,
    the arm driven through it."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String

    resources = DEMOS / "demo_resources"
    args = [
        "--worlds", "1", "--namespace", "", "--backend", "cpu",
        "--ros2-control", f"{DEMOS / 'demo_resources' / 'robot' / 'test_robot.urdf'} use_mjcf_from_topic:=true",
        "--mujoco-inputs", str(resources / "mjcf_generation" / "test_inputs.xml"),
        "--scene", str(resources / "scenes" / "scene_info.xml"),
        "--controllers", str(DEMOS / "config" / "controllers.yaml"),
    ]  # fmt: skip
    with Fleet(domain_id(88), args, tmp_path / "generated.log") as robot:
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        description = robot.latest(String, "/mujoco_robot_description", qos=latched)
        robot.wait(lambda: description.count > 0, 40, "/mujoco_robot_description")
        assert "<mujoco" in description.msg.data and '<site name="ee_link"' in description.msg.data
        js = robot.latest(ros["JointState"], "/joint_states")
        robot.wait(lambda: js.count > 0, 20, "/joint_states")
        _controllers_running(robot, ros)
        _command(robot, ros, "/position_controller/commands", [0.5, -0.5], {"joint1": 0.5, "joint2": -0.5}, js)


def test_mjcf_generation_from_the_robot_description_topic(tmp_path, ros):
    """robot_launch_mjcf_generation_from_robot_description_test.py (use_pid:=true
    use_mjcf_from_topic:=true): the URDF published latched on /robot_description, as
    robot_state_publisher does, and taken from there (--robot-description-topic): compiled to
    MJCF, the PID configuration's interfaces, the arm driven."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String

    from batchsim.model.description import expand_xacro

    urdf = expand_xacro(DEMOS / "demo_resources" / "robot" / "test_robot.urdf", {"use_pid": "true", "use_mjcf_from_topic": "true"})
    args = [
        "--worlds", "1", "--namespace", "", "--backend", "cpu", "--robot-description-topic", "/robot_description",
        "--controllers", str(DEMOS / "config" / "controllers.yaml"),
    ]  # fmt: skip
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    with Fleet(domain_id(89), args, tmp_path / "from_topic.log") as robot:
        publisher = robot.node.create_publisher(String, "/robot_description", latched)
        publisher.publish(String(data=urdf))
        description = robot.latest(String, "/mujoco_robot_description", qos=latched)
        robot.wait(lambda: description.count > 0, 60, "/mujoco_robot_description")
        assert "<mujoco" in description.msg.data and '<site name="ee_link"' in description.msg.data
        reply = robot.call(
            ros["cm"].ListHardwareInterfaces, "/controller_manager/list_hardware_interfaces", ros["cm"].ListHardwareInterfaces.Request()
        )
        command = sorted(i.name for i in reply.command_interfaces)
        assert command == sorted(["joint1/position", "joint2/position", "gripper_left_finger_joint/position",
                                  "joint1/velocity", "joint2/velocity"])  # fmt: skip
        js = robot.latest(ros["JointState"], "/joint_states")
        robot.wait(lambda: js.count > 0, 20, "/joint_states")
        _controllers_running(robot, ros)
        _command(robot, ros, "/position_controller/commands", [0.5, -0.5], {"joint1": 0.5, "joint2": -0.5}, js)
        # the topic read from keeps its one latched publisher (before: batchsim published a second
        # description there once someone subscribed, and RViz got whichever came last)
        seen = robot.latest(String, "/robot_description", qos=latched)
        robot.wait(lambda: seen.count > 0, 10, "/robot_description")
        time.sleep(3.0)  # a publisher made on request comes within a second of the subscriber
        assert robot.node.count_publishers("/robot_description") == 1
        robot.node.destroy_publisher(publisher)


def test_no_robot_description_on_the_topic_is_one_line_and_exit_2(tmp_path):
    import os
    import subprocess
    import sys

    from ros_fleet import LOCALHOST, release_domain

    domain = domain_id(87)
    try:
        env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
        done = subprocess.run(
            [sys.executable, "-m", "batchsim.cli", "--robot-description-topic", "/robot_description",
             "--robot-description-timeout", "1", "--quiet"],
            capture_output=True, text=True, timeout=60, env=env,
        )  # fmt: skip
        lines = [line for line in done.stderr.splitlines() if "waiting for" not in line]
        assert done.returncode == 2 and len(lines) == 1, done.stderr
        assert lines[0].startswith(
            "batchsim: error: --robot-description-topic /robot_description: no std_msgs/String on /robot_description within 1 s"
        ), lines
    finally:
        release_domain(domain)
