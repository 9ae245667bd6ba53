"""mujoco_ros2_control's own robots and files (tests/upstream, unchanged) read as upstream reads
them: the plugin YAML whole, the URDF's camera and lidar params, the model named by the
`mujoco_model` hardware param, lidars of the expanded description. No ROS here; the
behaviour over ROS is tests/test_mujoco_ros2_control_ros.py's.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import batchsim
from batchsim.sensors import SensorConfig, SensorConfigError, SensorSuite

DEMOS = Path(__file__).parent / "upstream" / "mujoco_ros2_control_demos"
URDF = DEMOS / "demo_resources" / "robot" / "test_robot.urdf"
SCENE = DEMOS / "demo_resources" / "scenes" / "scene.xml"
PLUGINS = DEMOS / "config" / "mujoco_ros2_control_plugins.yaml"


def _suite(config: SensorConfig | None = None, ros2_control: Path = URDF) -> SensorSuite:
    spec = batchsim.load(str(SCENE), ros2_control=str(ros2_control))
    return SensorSuite.build(spec, 1, config)


def test_the_demos_plugin_yaml_loads_unchanged():
    # before: "mujoco_camera_plugin.camera: unknown key 'policy'", then lidar_publish_rate read as a lidar
    config = SensorConfig.load(PLUGINS)
    suite = _suite(config)
    camera = suite.camera("camera")
    assert (camera.frame_id, camera.image_topic, camera.depth_topic, camera.info_topic) == (
        "camera_color_optical_frame",  # the YAML's, over the URDF's camera_color_mujoco_frame
        "/camera/color/image_raw",
        "/camera/aligned_depth_to_color/image_raw",
        "/camera/color/camera_info",
    )
    assert suite.camera_rate == 6.0 and suite.lidar_rate == 5.0  # camera_publish_rate, lidar_publish_rate
    lidar = suite.lidar("lidar")
    assert (lidar.frame_id, lidar.topic, lidar.range_min, lidar.range_max) == ("lidar_sensor_frame", "/scan", 0.05, 10.0)
    assert (lidar.angle_min, lidar.angle_max, lidar.angle_increment) == (-0.3, 0.3, 0.025)
    # the plugins batchsim does not run are named, with what to use instead
    warned = "\n".join(suite.config.warnings)
    assert "heart_beat_plugin: mujoco_ros2_control_plugins/HeartbeatPublisherPlugin is not run" in warned
    assert "free_joint_state_publisher: mujoco_ros2_control_plugins/FreeJointStatePublisherPlugin is not run" in warned


def test_the_base_velocity_plugin_is_run_not_warned_of():
    # before: "BaseVelocityPlugin is not run by batchsim: /cmd_vel does not move the base"
    config = SensorConfig.load(DEMOS / "config" / "mujoco_ros2_control_plugins_base_velocity.yaml")
    assert config.warnings == [] and config.base_velocity.body == "base_link"  # tests/test_base_velocity.py


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_demo_05_starts_and_a_bad_base_velocity_param_stops_it_in_one_line(tmp_path):
    resources = DEMOS / "demo_resources"
    args = [
        "--model", str(resources / "scenes" / "scene_mobile_base.xml"),
        "--ros2-control", str(resources / "mobile_base" / "mobile_base.urdf"),
        "--controllers", str(DEMOS / "config" / "controllers_base_velocity.yaml"),
        "--worlds", "2", "--backend", "cpu", "--no-ros", "--quiet", "--duration", "0.1",
    ]  # fmt: skip
    plugins = DEMOS / "config" / "mujoco_ros2_control_plugins_base_velocity.yaml"
    done = _cli(*args, "--sensors", str(plugins))
    assert done.returncode == 0 and "warning" not in done.stderr, done.stderr
    done = _cli("info", args[1], "--ros2-control", args[3], "--sensors", str(plugins))
    assert "base velocity plugin base_velocity_plugin: body 'base_link' held at <ns>/cmd_vel (Twist)" in done.stdout
    bad = tmp_path / "plugins.yaml"
    bad.write_text(plugins.read_text().replace("body: base_link", "body: chassis"))
    done = _cli(*args, "--sensors", str(bad))
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(f"batchsim: error: {bad}: /**.ros__parameters.mujoco_plugins.base_velocity_plugin.body: no body 'chassis'")


def test_the_urdfs_camera_and_lidar_params_are_honoured():
    # before: the camera on camera/image_raw and the lidar's range_max 1000 where the URDF says 10
    suite = _suite()
    camera = suite.camera("camera")
    assert (camera.frame_id, camera.image_topic, camera.info_topic) == (
        "camera_color_mujoco_frame",
        "/camera/color/image_raw",
        "/camera/color/camera_info",
    )
    lidar = suite.lidar("lidar")
    assert (lidar.topic, lidar.range_min, lidar.range_max, lidar.frame_id) == ("/scan", 0.05, 10.0, "lidar_sensor_frame")


@pytest.mark.parametrize(
    "plugin, message",
    [
        ({"mujoco_camera_plugin": {"type": "mujoco_ros2_control_plugins/CameraPlugin", "camera": {"policy": "sometimes"}}},
         "camera.policy: streaming, polled or disabled, got 'sometimes'"),
        ({"lidar": {"type": "mujoco_ros2_control_plugins/RangefinderLidarPlugin", "lidar": {"laser_topic": "/x"}}},
         "lidar.lidar: unknown key 'laser_topic'"),
        ({"lidar": {"type": "mujoco_ros2_control_plugins/RangefinderLidarPlugin", "lidar": {"topic": "/a", "laserscan_topic": "/b"}}},
         "both 'laserscan_topic' and its older spelling 'topic'"),
    ],
)  # fmt: skip
def test_a_bad_plugin_key_is_one_line_naming_it(plugin, message):
    with pytest.raises(SensorConfigError, match=message) as e:
        SensorConfig.load({"/**": {"ros__parameters": {"mujoco_plugins": plugin}}})
    assert "\n" not in str(e.value)


def test_an_unknown_plugin_type_is_named():
    config = SensorConfig.load({"/**": {"ros__parameters": {"mujoco_plugins": {"mine": {"type": "pkg/Thing"}}}}})
    assert config.warnings == ["<sensor config>: /**.ros__parameters.mujoco_plugins.mine: plugin type 'pkg/Thing' is unknown to batchsim: not run"]


LIDAR_XACRO = """<?xml version="1.0"?>
<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="r">
  <xacro:arg name="with_lidar" default="false"/>
  <xacro:if value="$(arg with_lidar)">
    <mujoco_inputs><processed_inputs>
      <lidar ref_site="{site}" sensor_name="fan" min_angle="-0.3" max_angle="0.3" angle_increment="0.1"/>
    </processed_inputs></mujoco_inputs>
  </xacro:if>
  <ros2_control name="S" type="system">
    <hardware><plugin>mujoco_ros2_control/MujocoSystemInterface</plugin></hardware>
    <joint name="joint1"><command_interface name="position"/><state_interface name="position"/></joint>
  </ros2_control>
</robot>
"""


def test_lidars_are_read_from_the_expanded_description(tmp_path):
    # before: the <lidar> inside a false xacro:if appeared (read before expansion)
    path = tmp_path / "robot.urdf.xacro"
    path.write_text(LIDAR_XACRO.format(site="lidar_sensor_frame"))
    assert "fan" not in _suite(ros2_control=path).lidars
    spec = batchsim.load(str(SCENE), ros2_control=f"{path} with_lidar:=true")
    assert SensorSuite.build(spec, 1).lidar("fan").ncol == 6  # (max - min) / increment, as upstream generates them


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "batchsim.cli", *args], capture_output=True, text=True, timeout=120, cwd=cwd
    )


def test_the_model_comes_from_the_mujoco_model_param():
    # `$(find mujoco_ros2_control_demos)` resolves to tests/upstream/mujoco_ros2_control_demos
    out = _cli("info", "--ros2-control", str(URDF), "--sensors", str(PLUGINS))
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"model      scene  ({SCENE})")
    assert "-> /camera/color/image_raw" in out.stdout and "range 0.05..10 m -> /scan" in out.stdout
    assert "HeartbeatPublisherPlugin is not run by batchsim" in out.stdout
    # the URDF given as the model reads its mujoco_model too, as `--ros2-control` does (before:
    # the URDF compiled alone, with no actuators, and "camera is not in the model")
    same = _cli("info", str(URDF), "--sensors", str(PLUGINS))
    assert same.returncode == 0, same.stderr
    assert same.stdout == out.stdout


# --- a robot described only by a URDF, compiled as mujoco_ros2_control's generation tool does ---
RESOURCES = DEMOS / "demo_resources"


def _kinematics(m):
    import mujoco

    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    mujoco.mj_camlight(m, d)
    return d


def test_a_urdf_compiles_to_the_mjcf_upstreams_tool_generates():
    """test_robot.urdf + mjcf_generation/test_inputs.xml against robot/test_robot.xml, which is
    upstream's tool's output for them (plus two free cubes added by hand): the same links, sites,
    masses, camera pose and lidar rays."""
    import mujoco
    import numpy as np

    spec = batchsim.load(f"{URDF} use_mjcf_from_topic:=true", mujoco_inputs=RESOURCES / "mjcf_generation" / "test_inputs.xml")
    mine, theirs = spec.mjmodel, mujoco.MjModel.from_xml_path(str(RESOURCES / "robot" / "test_robot.xml"))
    dm, dt = _kinematics(mine), _kinematics(theirs)
    assert [mine.joint(j).name for j in range(mine.njnt)] == [theirs.joint(j).name for j in range(4)]
    for k in range(theirs.nsite):
        name = theirs.site(k).name
        s = mujoco.mj_name2id(mine, mujoco.mjtObj.mjOBJ_SITE, name)
        assert s >= 0, f"site {name} missing"
        np.testing.assert_allclose(dm.site_xpos[s], dt.site_xpos[k], atol=1e-6, err_msg=name)
        np.testing.assert_allclose(dm.site_xmat[s], dt.site_xmat[k], atol=1e-5, err_msg=name)
    for b in ("upperarm", "forearm", "gripper_left_finger"):
        assert mine.body(b).mass[0] == pytest.approx(theirs.body(b).mass[0])
    np.testing.assert_allclose(dm.cam_xpos, dt.cam_xpos, atol=1e-6)
    np.testing.assert_allclose(dm.cam_xmat, dt.cam_xmat, atol=1e-5)
    assert mine.opt.integrator == theirs.opt.integrator and mine.nu == theirs.nu == 3
    assert spec.command_interfaces == ["joint1/position", "joint2/position", "gripper_left_finger_joint/position"]
    assert not spec.problems
    assert list(SensorSuite.build(spec, 1).lidars) == ["lidar"]  # the URDF's <lidar>, as replicated rangefinders


def test_a_urdfs_own_mujoco_inputs_and_the_cli(tmp_path):
    source = f"{URDF} use_pid:=true use_mjcf_from_topic:=true"
    spec = batchsim.load(source)  # the inputs inside the URDF (raw, processed, scene)
    assert spec.mjmodel.nu == 3 and spec.mjmodel.ncam == 1 and spec.path == URDF
    # use_pid's velocity interfaces on the inputs' position servos: listed, as upstream lists them
    assert not spec.problems and {"joint1/velocity", "joint2/velocity"} <= set(spec.command_interfaces)
    assert any("joint1/velocity on position actuator 'joint1'" in w for w in spec.warnings)
    out = _cli("info", "--ros2-control", f"{URDF} use_mjcf_from_topic:=true", "--mujoco-inputs",
               str(RESOURCES / "mjcf_generation" / "test_inputs.xml"), "--scene", str(RESOURCES / "scenes" / "scene_info.xml"))  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"model      two_dof_robot  ({URDF})")
    mjcf = _cli("info", str(URDF), "--mujoco-inputs", str(RESOURCES / "mjcf_generation" / "test_inputs.xml"), "--mjcf")
    assert mjcf.returncode == 0 and mjcf.stdout.startswith('<mujoco model="two_dof_robot">')
    assert '<site name="ee_link"' in mjcf.stdout


@pytest.mark.parametrize(
    "urdf, message",
    [
        ('<robot name="r"><link name="a"><visual><geometry><mesh filename="a.dae"/></geometry></visual></link></robot>',
         "mesh 'a.dae': MuJoCo reads STL, OBJ and MSH meshes, not .dae"),
        ('<robot name="r"><link name="a"/><joint name="j" type="revolute"><parent link="a"/><child link="b"/></joint></robot>',
         "MuJoCo cannot compile this URDF"),
        ('<robot name="r"><link name="a"/><mujoco_inputs><processed_inputs><camera site="nowhere" name="c"/>'
         '</processed_inputs></mujoco_inputs></robot>', "<camera name='c'>: no link (site) named 'nowhere' in the URDF"),
    ],
)  # fmt: skip
def test_a_bad_urdf_is_one_line_and_exit_2(tmp_path, urdf, message):
    path = tmp_path / "robot.urdf"
    path.write_text(urdf)
    with pytest.raises(batchsim.ModelError, match=re.escape(message)) as e:
        batchsim.load(str(path))
    assert "\n" not in str(e.value) and str(path) in str(e.value)
    out = _cli("info", str(path))
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and message.split(":")[0] in out.stderr


# --- transmissions: robot_launch_transmission(_pid)_test.py's setup, as 04_transmissions.launch.py makes it ---


def transmission_robot(tmp_path: Path, use_pid: bool = False) -> Path:
    """test_robot.urdf with use_transmissions:=true, its MJCF's joint1/joint2 renamed
    actuator1/actuator2 and the URDF pointed at it: what upstream's launch file
    (process_transmission_files) hands its node as robot_description. Returns the URDF; the
    model is its `mujoco_model` (tmp_path / "scene.xml")."""
    from batchsim.model.description import expand_xacro

    text = expand_xacro(URDF, {"use_transmissions": "true", "use_pid": "true" if use_pid else "false"})
    model = Path(text.split('mujoco_model">')[1].split("</param>")[0].strip())
    scene = model.read_text()
    include = scene.split('<include file="')[1].split('"/>')[0].strip()
    robot = (model.parent / include).read_text().replace('"joint1"', '"actuator1"').replace('"joint2"', '"actuator2"')
    (tmp_path / "robot.xml").write_text(robot)
    (tmp_path / "scene.xml").write_text(scene.replace(include, str(tmp_path / "robot.xml")))
    urdf = tmp_path / "test_robot.urdf"
    urdf.write_text(text.replace(str(model), str(tmp_path / "scene.xml")))
    return urdf


@pytest.mark.parametrize("use_pid", [False, True], ids=["position", "pid"])
def test_a_differential_transmission_drives_joints_through_two_actuators(tmp_path, use_pid):
    """robot_launch_transmission_test.py's test_arm and hardware interfaces, through the Python API:
    joint targets 0.5/-0.5 reached, the actuators where the differential puts them
    (reductions 2.0/0.5: 0.5*2 - 0.5*0.5 = 0.75 and 0.5*2 + 0.5*0.5 = 1.25), efforts reported."""
    urdf = transmission_robot(tmp_path, use_pid)
    spec = batchsim.load(str(tmp_path / "scene.xml"), ros2_control=str(urdf))
    assert not spec.problems
    joints = [f"joint{j}/{k}" for j in (1, 2) for k in (("position", "velocity") if use_pid else ("position",))]
    assert spec.command_interfaces == [*joints, "gripper_left_finger_joint/position"]
    if use_pid:  # the PIDs are the actuators' (pid_gains.position.actuator1 ...), as upstream's
        modes = {c.name: c.mode.value for c in spec.actuator_commands}
        assert modes["actuator1/position"] == modes["actuator2/position"] == "position_pid"
    assert [n for n, _, _ in spec.actuator_joints] == ["actuator1", "actuator2", "gripper_left_finger_joint",
                                                      "gripper_right_finger_joint"]  # fmt: skip
    sim = batchsim.make(spec, 2, "cpu")
    sim.configure()
    sim.activate()
    names, state = sim.export_command_interfaces(), sim.export_state_interfaces()
    sim.command[0, names.index("joint1/position")] = 0.5
    sim.command[0, names.index("joint2/position")] = -0.5
    for _ in range(400):
        sim.read()
        sim.write()
        sim.step(10)
    sim.read()
    joint = {n: sim.state[:, state.index(n)] for n in ("joint1/position", "joint2/position", "joint1/effort", "joint1/torque")}
    assert joint["joint1/position"][0] == pytest.approx(0.5, abs=0.05)
    assert joint["joint2/position"][0] == pytest.approx(-0.5, abs=0.05)
    # world 1 holds its start (a P-only PID sags a little under gravity: upstream's gains)
    assert abs(joint["joint1/position"][1]) < 0.15 and abs(joint["joint2/position"][1]) < 0.15
    assert joint["joint1/effort"][0] == joint["joint1/torque"][0] != 0.0
    na = len(spec.actuator_joints)
    positions, efforts = sim.actuator_states[0, :na], sim.actuator_states[0, 2 * na :]
    assert positions[:2] == pytest.approx([0.75, 1.25], abs=0.05)
    assert np.abs(efforts).max() > 1e-6


def test_the_maps_are_transmission_interfaces():
    """ros2_control's formulas (differential_transmission.hpp, simple_transmission.hpp), with
    offsets and actuator reductions: a joint command read back through the state map is itself,
    and the power through the transmission is conserved (joint effort . velocity = actuator's)."""
    from batchsim.model import InterfaceKind as K
    from batchsim.model import Transmission, TransmissionKind

    jr, ar, off = (2.0, 0.5), (1.5, -3.0), (0.1, -0.2)
    diff = Transmission("d", TransmissionKind.DIFFERENTIAL, ("j1", "j2"), ("a1", "a2"),
                        ((jr[0] * ar[0], jr[1] * ar[0]), (jr[0] * ar[1], -jr[1] * ar[1])), off)  # fmt: skip
    j = np.array([0.3, -0.7])
    a_of, a_b = diff.actuator_from_joint(K.POSITION)
    a = a_of @ j + a_b
    jj = j - off  # upstream: act[0] = (j0 jr0 + j1 jr1) ar0, act[1] = (j0 jr0 - j1 jr1) ar1, offsets removed first
    assert a == pytest.approx([(jj[0] * jr[0] + jj[1] * jr[1]) * ar[0], (jj[0] * jr[0] - jj[1] * jr[1]) * ar[1]])
    j_of, j_b = diff.joint_from_actuator(K.POSITION)
    assert j_of @ a + j_b == pytest.approx(j)
    v = np.array([1.1, 0.4])
    av = diff.actuator_from_joint(K.VELOCITY)[0] @ v
    ae = np.array([2.0, -5.0])
    je = diff.joint_from_actuator(K.EFFORT)[0] @ ae
    assert je == pytest.approx([jr[0] * (ae[0] * ar[0] + ae[1] * ar[1]), jr[1] * (ae[0] * ar[0] - ae[1] * ar[1])])
    assert je @ v == pytest.approx(ae @ av)
    assert diff.actuator_from_joint(K.EFFORT)[0] @ je == pytest.approx(ae)
    simple = Transmission("s", TransmissionKind.SIMPLE, ("j",), ("a",), ((4.0,),), (0.5,))
    a_of, a_b = simple.actuator_from_joint(K.POSITION)
    assert a_of @ [1.0] + a_b == pytest.approx([(1.0 - 0.5) * 4.0])  # (joint - offset) * reduction
    assert simple.joint_from_actuator(K.EFFORT)[0] @ [3.0] == pytest.approx([12.0])  # effort * reduction


def _one_transmission(tmp_path: Path, body: str) -> Path:
    path = transmission_robot(tmp_path)
    text = path.read_text()
    start, end = text.index("<transmission"), text.index("</transmission>") + len("</transmission>")
    path.write_text(text[:start] + body + text[end:])
    return path


@pytest.mark.parametrize(
    "body, message",
    [
        ('<transmission name="t"><plugin>transmission_interface/FourBarLinkageTransmission</plugin>'
         '<joint name="joint1"/><joint name="joint2"/><actuator name="actuator1"/><actuator name="actuator2"/></transmission>',
         "transmission 't': plugin 'transmission_interface/FourBarLinkageTransmission' is not one batchsim runs"),
        ('<transmission name="t"><plugin>transmission_interface/SimpleTransmission</plugin>'
         '<joint name="joint1"><mechanical_reduction>0</mechanical_reduction></joint><actuator name="actuator1"/></transmission>',
         "transmission 't': 'joint1': mechanical_reduction cannot be zero"),
        ('<transmission name="t"><plugin>transmission_interface/DifferentialTransmission</plugin>'
         '<joint name="joint1"/><joint name="joint2"/><actuator name="actuator1"/><actuator name="motor9"/></transmission>',
         "transmission 't': actuator 'motor9': the model has no actuator, and no actuated joint, of that name"),
        ('<transmission name="t"><plugin>transmission_interface/DifferentialTransmission</plugin>'
         '<joint name="joint1"/><actuator name="actuator1"/></transmission>',
         "transmission 't': a DifferentialTransmission takes 2 joint(s) and 2 actuator(s), got 1 and 1"),
    ],
)  # fmt: skip
def test_a_transmission_that_cannot_be_built_is_one_line_and_exit_2(tmp_path, body, message):
    urdf = _one_transmission(tmp_path, body)
    spec = batchsim.load(str(tmp_path / "scene.xml"), ros2_control=str(urdf))
    assert any(message in p for p in spec.problems), spec.problems
    out = _cli("--worlds", "1", "--no-ros", "--duration", "0.1", "--ros2-control", str(urdf))
    assert out.returncode == 2, out.stderr
    errors = [line for line in out.stderr.splitlines() if "warning" not in line]
    assert len(errors) == 1 and message in errors[0], out.stderr
