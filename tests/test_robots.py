"""Real robots, unchanged, tried as a user would: the MuJoCo Menagerie robots in
../shared/robots and those that ship inside installed packages, and ros2_control
configuration written the way mujoco_ros2_control's users write it, over real ROS 2.

Tests that need ../shared/robots skip, saying so, only where ../shared is absent (CI has it).
"""

from __future__ import annotations

import importlib.util
import sys
import tarfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import need

import batchsim
from batchsim.loop import SimLoop

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "robots"
sys.path.insert(0, str(ROOT))  # benchmarks/robots.py, the robot-check script CI runs here


def _installed(module: str, *parts: str) -> Path:
    spec = importlib.util.find_spec(module)
    return Path(spec.origin).parent.joinpath(*parts)


@pytest.fixture(scope="module")
def robots(tmp_path_factory) -> Path:
    """../shared/robots unpacked: <tmp>/unitree_go2/scene.xml, ..."""
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} is absent (../shared holds the Menagerie robots; CI has it)")
    out = tmp_path_factory.mktemp("robots")
    for archive in sorted(SHARED.glob("*.tar.xz")):
        with tarfile.open(archive) as tar:
            tar.extractall(out, filter="data")
    return out


def test_every_robot_runs_two_seconds_on_cpu_from_its_keyframe(robots, capsys):
    from benchmarks.robots import main

    dirs = [
        robots,
        _installed("mujoco", "mjx", "test_data", "barkour_v0", "assets"),
        _installed("mujoco", "mjx", "test_data", "shadow_hand"),
        _installed("mujoco_warp", "test_data", "aloha_pot"),
    ]
    rc = main([*map(str, dirs), "--backends", "cpu", "--seconds", "2", "--worlds", "2"])
    out = capsys.readouterr().out
    lines = {line.split()[1]: line for line in out.splitlines()}
    assert "starts in keyframe 'home'" in lines["unitree_go2/scene.xml"]
    assert "starts in keyframe 'home'" in lines["universal_robots_ur5e/scene.xml"]
    assert "aloha_pot/scene.xml" in lines and "shadow_hand/scene_right.xml" in lines
    # finite is not enough: the Go2's torque motors hold its keyframe's ctrl as torques, and it
    # folds to the floor; that is a failure, named with its reason (a controller holds it up:
    # test_robots' PID test below)
    failed = sorted(name for name, line in lines.items() if line.startswith("FAIL"))
    assert rc == 1 and failed == ["unitree_go2/scene.xml"], out
    assert "COLLAPSES: its base fell from 0.27 m" in lines["unitree_go2/scene.xml"]
    assert "torque motors" in lines["unitree_go2/scene.xml"]
    assert "holds its start pose" in lines["universal_robots_ur5e/scene.xml"]


def test_home_keyframe_and_the_robots_own_base(robots):
    go2 = batchsim.load(robots / "unitree_go2" / "scene.xml")
    assert go2.initial.keyframe == "'home'" and go2.initial.qpos[2] == pytest.approx(0.27)
    assert go2.floating_base is not None and go2.floating_base.body == "base"
    ur5e = batchsim.load(robots / "universal_robots_ur5e" / "scene.xml")
    assert ur5e.initial.qpos[1] == pytest.approx(-1.5708) and ur5e.floating_base is None
    # the shadow hand's fingers are tendon-driven: their actuators are command interfaces
    hand = batchsim.load(robots / "shadow_hand" / "scene_right.xml")
    assert "rh_A_FFJ0/position" in hand.command_interfaces
    # ALOHA's pot is a free prop: not the base of a fixed-base bimanual robot
    aloha = batchsim.load(_installed("mujoco_warp", "test_data", "aloha_pot", "scene.xml"))
    assert aloha.floating_base is None


def test_warp_runs_a_menagerie_arm_and_mjx_names_what_it_cannot_simulate(robots, capsys):
    from benchmarks.robots import main

    need("mujoco_warp")
    scene = robots / "universal_robots_ur5e" / "scene.xml"
    assert main([str(scene), "--backends", "warp", "--seconds", "0.2", "--worlds", "2"]) == 0
    assert "ok   universal_robots_ur5e/scene.xml" in capsys.readouterr().out
    need("jax")
    with pytest.raises(batchsim.backends.UnsupportedModel, match=r"mjx backend cannot simulate .*backends that can: cpu, warp"):
        batchsim.make(robots / "unitree_go2" / "scene.xml", 2, "mjx")


GO2_JOINTS = [f"{leg}_{part}_joint" for leg in ("FL", "FR", "RL", "RR") for part in ("hip", "thigh", "calf")]


def _go2_description(tmp_path: Path) -> Path:
    joints = "\n".join(
        f'<joint name="{j}"><command_interface name="position"/><state_interface name="position"/>'
        f'<state_interface name="velocity"/></joint>'
        for j in GO2_JOINTS
    )
    (tmp_path / "go2_pids.yaml").write_text(
        "/**:\n  ros__parameters:\n    pid_gains:\n      position:\n"
        + "".join(f"        {j}: {{p: 60.0, i: 0.0, d: 3.0, u_clamp_max: 45.0, u_clamp_min: -45.0}}\n" for j in GO2_JOINTS)
    )
    path = tmp_path / "go2.ros2_control.xml"
    path.write_text(
        '<robot name="go2"><ros2_control name="Go2" type="system"><hardware>'
        "<plugin>mujoco_ros2_control/MujocoSystemInterface</plugin>"
        '<param name="pids_config_file">go2_pids.yaml</param></hardware>'
        f"{joints}</ros2_control></robot>"
    )
    return path


def test_a_quadruped_is_held_standing_by_position_commands_through_pids(robots, tmp_path):
    scene = robots / "unitree_go2" / "scene.xml"
    sim = batchsim.make(scene, 2, "cpu", ros2_control=_go2_description(tmp_path))
    assert sim.export_command_interfaces() == [f"{j}/position" for j in GO2_JOINTS]
    sim.configure()
    sim.activate()
    assert sim.command[0, 1] == pytest.approx(0.9)  # each leg holds the home keyframe
    SimLoop(sim, control_rate=100, rtf=0, duration=3.0).run()
    sim.read()
    assert sim.base_state[:, 2] == pytest.approx([0.256, 0.256], abs=0.02)  # home stands at 0.27
    # the same motors given zero torque (their own effort interfaces) fold under the robot
    limp = batchsim.make(scene, 1, "cpu")
    limp.configure()
    limp.activate()
    limp.command[:] = 0.0
    SimLoop(limp, control_rate=100, rtf=0, duration=3.0).run()
    limp.read()
    assert limp.base_state[0, 2] < 0.15


# --- over ROS 2 ---


@pytest.fixture(scope="module")
def ros() -> SimpleNamespace:
    """The test fleet and the messages the tests over ROS 2 use, imported for those tests only,
    so that the plain tests of this file run where ROS is absent: a missing rclpy skips them,
    or fails them under BATCHSIM_FORCE_BACKENDS=1 (CI)."""
    fleet = need("ros_fleet")
    from geometry_msgs.msg import PoseStamped
    from rclpy.duration import Duration
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    return SimpleNamespace(
        Fleet=fleet.Fleet, domain_id=fleet.domain_id, Duration=Duration, PoseStamped=PoseStamped,
        JointState=JointState, Float64MultiArray=Float64MultiArray, JointTrajectory=JointTrajectory,
        JointTrajectoryPoint=JointTrajectoryPoint,
    )  # fmt: skip


UR5E_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]

UR5E_YAML = f"""controller_manager:
  ros__parameters:
    update_rate: 500
    joint_state_broadcaster:
      type: joint_state_broadcaster/JointStateBroadcaster
    scaled_joint_trajectory_controller:
      type: joint_trajectory_controller/JointTrajectoryController

scaled_joint_trajectory_controller:
  ros__parameters:
    joints: {UR5E_JOINTS}
    command_interfaces: [position]
    state_interfaces: [position, velocity]
"""


@pytest.mark.ros
def test_a_menagerie_arm_follows_a_joint_trajectory_over_ros(robots, tmp_path, ros):
    yaml = tmp_path / "ur5e_controllers.yaml"
    yaml.write_text(UR5E_YAML)
    args = ["--worlds", "2", "--model", str(robots / "universal_robots_ur5e" / "scene.xml"), "--controllers", str(yaml)]
    with ros.Fleet(ros.domain_id(80), args, tmp_path / "ur5e.log") as fleet:
        js = [fleet.latest(ros.JointState, f"/world_{w}/joint_states") for w in range(2)]
        fleet.wait(lambda: all(s.count > 2 for s in js), 30, "joint_states from both worlds")
        home = list(js[1].msg.position)
        assert home[1] == pytest.approx(-1.5708, abs=0.02)  # it starts in its home keyframe
        goal = list(home)
        goal[0] = home[0] + 0.5
        msg = ros.JointTrajectory(joint_names=UR5E_JOINTS)
        msg.points = [ros.JointTrajectoryPoint(positions=goal, time_from_start=ros.Duration(seconds=1.0).to_msg())]
        topic = "/world_1/scaled_joint_trajectory_controller/joint_trajectory"
        fleet.publish(ros.JointTrajectory, topic, msg)
        fleet.wait_subscribed(topic)
        fleet.publish(ros.JointTrajectory, topic, msg)
        fleet.wait(lambda: abs(js[1].msg.position[0] - goal[0]) < 0.02, 30, f"world 1 at its goal\n{js[1].msg}")
        assert js[0].msg.position[0] == pytest.approx(home[0], abs=0.01)  # world 0 holds home
        assert fleet.close() == 0, fleet.log()


# mujoco_ros2_control's layout: tendon gripper named after its joint, the type in each
# controller's own block, a pose sensor by mujoco_type, a position PID on a motor
DEMO_MJCF = """<mujoco model="two_dof">
  <compiler angle="radian"/>
  <option timestep="0.002" integrator="implicitfast"><flag contact="disable"/></option>
  <worldbody>
    <body name="upperarm">
      <joint name="joint1" axis="0 0 1" damping="2"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.04" mass="2"/>
      <body name="forearm" pos="0.5 0 0">
        <joint name="joint2" axis="0 0 1" damping="1"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="1"/>
        <site name="ee_link" pos="0.4 0 0"/>
        <body name="left" pos="0.4 0.03 0"><joint name="gripper_left_finger_joint" type="slide" axis="0 1 0" range="-0.03 0.01"/>
          <geom type="box" size="0.01 0.005 0.02" mass="0.05"/></body>
        <body name="right" pos="0.4 -0.03 0"><joint name="gripper_right_finger_joint" type="slide" axis="0 1 0" range="-0.01 0.03"/>
          <geom type="box" size="0.01 0.005 0.02" mass="0.05"/></body>
      </body>
    </body>
  </worldbody>
  <tendon><fixed name="split"><joint joint="gripper_left_finger_joint" coef="0.5"/><joint joint="gripper_right_finger_joint" coef="-0.5"/></fixed></tendon>
  <equality><joint joint1="gripper_left_finger_joint" joint2="gripper_right_finger_joint" polycoef="0 -1 0 0 0"/></equality>
  <actuator>
    <position name="joint1" joint="joint1" kp="400" dampratio="1" ctrlrange="-3 3"/>
    <motor name="joint2_motor" joint="joint2" ctrlrange="-20 20"/>
    <position name="gripper_left_finger_joint" tendon="split" kp="200" dampratio="1" ctrlrange="-0.03 0.01"/>
  </actuator>
  <sensor><framepos name="body_pos" objtype="site" objname="ee_link"/><framequat name="body_quat" objtype="site" objname="ee_link"/>
    <force name="wrist_force" site="ee_link"/><torque name="wrist_torque" site="ee_link"/></sensor>
</mujoco>"""

DEMO_URDF = """<?xml version="1.0"?>
<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="two_dof">
  <xacro:arg name="use_pid" default="false"/>
  <ros2_control name="MujocoSystem" type="system">
    <hardware>
      <plugin>mujoco_ros2_control/MujocoSystemInterface</plugin>
      <xacro:if value="$(arg use_pid)"><param name="pids_config_file">$(find demo_pkg)/config/pids.yaml</param></xacro:if>
      <param name="headless">true</param>
    </hardware>
    <joint name="joint1"><command_interface name="position"/>
      <state_interface name="position"><param name="initial_value">0.0</param></state_interface><state_interface name="velocity"/></joint>
    <joint name="joint2"><command_interface name="position"/>
      <state_interface name="position"><param name="initial_value">0.0</param></state_interface><state_interface name="torque"/></joint>
    <joint name="gripper_left_finger_joint"><command_interface name="position"/><state_interface name="position"/></joint>
    <joint name="gripper_right_finger_joint"><state_interface name="position"/></joint>
    <sensor name="pose"><param name="mujoco_type">pose</param><param name="mujoco_sensor_name">body</param>
      <state_interface name="position.x"/><state_interface name="position.y"/><state_interface name="position.z"/>
      <state_interface name="orientation.x"/><state_interface name="orientation.y"/><state_interface name="orientation.z"/>
      <state_interface name="orientation.w"/></sensor>
    <sensor name="wrist"><param name="mujoco_type">fts</param>
      <state_interface name="force.x"/><state_interface name="force.y"/><state_interface name="force.z"/>
      <state_interface name="torque.x"/><state_interface name="torque.y"/><state_interface name="torque.z"/></sensor>
  </ros2_control>
</robot>"""

DEMO_YAML = """controller_manager:
  ros__parameters:
    update_rate: 100

joint_state_broadcaster:
  ros__parameters:
    type: joint_state_broadcaster/JointStateBroadcaster

position_controller:
  ros__parameters:
    type: forward_command_controller/ForwardCommandController
    interface_name: position
    joints:
      - joint1
      - joint2

gripper_controller:
  ros__parameters:
    type: parallel_gripper_action_controller/GripperActionController
    joint: gripper_left_finger_joint

pose_broadcaster:
  ros__parameters:
    type: pose_broadcaster/PoseBroadcaster
    pose_name: pose
    frame_id: base
"""


# --- controller YAML as mujoco_ros2_control writes it, and its controllers ---

LAYOUT2 = """controller_manager:
  ros__parameters:
    update_rate: 100
arm_controller:
  ros__parameters:
    type: forward_command_controller/ForwardCommandController
    interface_name: position
    joints: [joint1]
    joints: [joint1]
joint_state_broadcaster:
  ros__parameters:
    type: joint_state_broadcaster/JointStateBroadcaster
mujocosystem:
  ros__parameters:
    pid_gains:
      position:
        joint2: {p: 1.0}
"""


DEMO_PIDS = """/**:
  ros__parameters:
    pid_gains:
      position:
        joint2: {p: 30.0, i: 5.0, d: 3.0, u_clamp_max: 20.0, u_clamp_min: -20.0}
"""


def _demo(tmp_path: Path) -> Path:
    """The mujoco_ros2_control-style robot in a package folder: (robot.xml, robot.urdf, ...)."""
    pkg = tmp_path / "demo_pkg"
    (pkg / "config").mkdir(parents=True)
    (pkg / "config" / "pids.yaml").write_text(DEMO_PIDS)
    (pkg / "robot.xml").write_text(DEMO_MJCF)
    (pkg / "robot.urdf").write_text(DEMO_URDF)
    (pkg / "controllers.yaml").write_text(DEMO_YAML)
    return pkg


def _demo_spec(tmp_path: Path) -> batchsim.RobotSpec:
    pkg = _demo(tmp_path)
    return batchsim.load(pkg / "robot.xml", ros2_control=f"{pkg / 'robot.urdf'} use_pid:=true")


def test_controllers_with_their_type_in_their_own_block_run(tmp_path):
    from batchsim.controllers import ForwardCommandController, JointStateBroadcaster, load_controllers

    spec = _demo_spec(tmp_path)
    manager = load_controllers(LAYOUT2, spec, 2)
    assert list(manager.controllers) == ["arm_controller", "joint_state_broadcaster"]
    assert isinstance(manager["arm_controller"], ForwardCommandController)
    assert isinstance(manager["joint_state_broadcaster"], JointStateBroadcaster)
    assert any("mujocosystem: pid_gains: ignored" in w for w in manager.warnings)


def test_a_declared_controller_that_cannot_run_stops_the_run(tmp_path):
    from batchsim.controllers import load_controllers

    spec = _demo_spec(tmp_path)
    with pytest.raises(batchsim.ConfigurationError, match="controller 'arm_controller': type: unknown type 'nope/Nope'"):
        load_controllers(LAYOUT2.replace("forward_command_controller/ForwardCommandController", "nope/Nope"), spec, 2)
    mixed = LAYOUT2.replace("update_rate: 100", "update_rate: 100\n    arm_controller:\n      type: position_controllers/JointGroupPositionController")
    with pytest.raises(batchsim.ConfigurationError, match="'arm_controller': type: .* in its own block but"):
        load_controllers(mixed, spec, 2)
    with pytest.raises(batchsim.ConfigurationError, match="pose_broadcaster.*pose_name: the model has no pose 'tool'"):
        load_controllers(DEMO_YAML.replace("pose_name: pose", "pose_name: tool"), spec, 2)


def test_pose_broadcaster_and_gripper_controller(tmp_path):
    from batchsim.controllers import load_controllers

    spec = _demo_spec(tmp_path)
    sim = batchsim.make(spec, 2, "cpu")
    sim.configure()
    sim.activate()
    manager = load_controllers(DEMO_YAML, spec, 2)
    loop = SimLoop(sim, control_rate=100, rtf=0, duration=1.0, participants=[manager])
    gripper = manager["gripper_controller"]
    gripper.set_goal(1, [-0.02, 0.0])
    with pytest.raises(ValueError, match="gripper_cmd must be"):
        gripper.set_goal(0, [np.nan, 1.0])
    loop.run()
    pose = manager["pose_broadcaster"]
    assert pose.position[:, 0] == pytest.approx([0.9, 0.9], abs=1e-3)  # the arm reaches along x
    assert pose.orientation[0] == pytest.approx([0, 0, 0, 1], abs=1e-6)
    assert gripper.measured[1, 0] == pytest.approx(-0.02, abs=0.003) and gripper.measured[0, 0] == pytest.approx(0, abs=0.003)
    topics = {t.topic for t in gripper.topics().inputs} | {t.topic for t in pose.topics().outputs}
    assert topics == {"gripper_controller/gripper_cmd", "pose_broadcaster/pose"}


def test_pids_scaled_commands_and_negated_sensors_agree_on_cpu_and_warp(tmp_path):
    need("mujoco_warp")
    spec = _demo_spec(tmp_path)
    runs = {}
    for backend in ("cpu", "warp"):
        sim = batchsim.make(spec, 2, backend)
        sim.configure()
        sim.activate()
        names = sim.export_command_interfaces()
        sim.command[1, names.index("joint1/position")] = 0.4
        sim.command[1, names.index("joint2/position")] = -0.3  # through the PID
        SimLoop(sim, control_rate=100, rtf=0, duration=0.3).run()
        sim.read()
        runs[backend] = sim.state.copy()
        sim.shutdown()
    names = spec.state_interfaces
    cols = [names.index(n) for n in ("joint1/position", "joint2/position", "wrist/force.x", "wrist/torque.z")]
    assert runs["warp"][:, cols] == pytest.approx(runs["cpu"][:, cols], rel=2e-3, abs=2e-3)
    raw = names.index("wrist/force.x")
    assert runs["cpu"][1, raw] != 0.0


@pytest.mark.ros
def test_mujoco_ros2_control_style_configuration_drives_the_robot_over_ros(tmp_path, ros):
    pkg = _demo(tmp_path)
    args = [
        "--worlds", "2", "--model", str(pkg / "robot.xml"),
        "--ros2-control", f"{pkg / 'robot.urdf'} use_pid:=true", "--controllers", str(pkg / "controllers.yaml"),
    ]
    with ros.Fleet(ros.domain_id(80), args, tmp_path / "demo.log") as fleet:
        js = [fleet.latest(ros.JointState, f"/world_{w}/joint_states") for w in range(2)]
        pose = fleet.latest(ros.PoseStamped, "/world_1/pose_broadcaster/pose")
        fleet.wait(lambda: all(s.count > 2 for s in js) and pose.count > 0, 30, "joint_states and the pose")
        names = list(js[1].msg.name)
        assert pose.msg.header.frame_id == "world_1/base" and pose.msg.pose.position.x == pytest.approx(0.9, abs=0.01)
        target = ros.Float64MultiArray(data=[0.6, -0.5])
        j1, j2 = names.index("joint1"), names.index("joint2")
        fleet.publish_until(
            ros.Float64MultiArray, "/world_1/position_controller/commands", target,
            lambda: abs(js[1].msg.position[j1] - 0.6) < 0.02 and abs(js[1].msg.position[j2] + 0.5) < 0.03,
            30, "world 1's arm at its target (joint2 through the PID)",
        )
        grip = ros.Float64MultiArray(data=[-0.02, 5.0])
        left, right = names.index("gripper_left_finger_joint"), names.index("gripper_right_finger_joint")
        fleet.publish_until(
            ros.Float64MultiArray, "/world_1/gripper_controller/gripper_cmd", grip,
            lambda: abs(js[1].msg.position[left] + 0.02) < 0.005, 30, "world 1's gripper closed",
        )
        assert js[1].msg.position[right] == pytest.approx(0.02, abs=0.005)  # the coupled finger follows
        assert np.allclose(js[0].msg.position[j1:j1 + 1], [0.0], atol=0.01)  # world 0 holds its start
        fleet.wait(lambda: pose.msg.pose.position.y > 0.3, 10, "the pose to follow the arm")
        assert fleet.close() == 0, fleet.log()
