"""Model loading: shipped models by name, MJCF extension and ros2_control blocks, errors."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import need

import batchsim
from batchsim import ConfigurationError, LifecycleState, ModelError
from batchsim.types import READ_FIELDS, StateSource

S = LifecycleState


@pytest.mark.parametrize("model", ["arm", "car", "quadruped"])
def test_shipped_models_stay_finite_for_10_seconds(model):
    sim = batchsim.make(model, 2, "cpu")
    sim.configure()
    sim.activate()
    sim.command[:] = 0.0
    sim.write()
    nstep = round(10.0 / sim.dt)
    sim.step(nstep)
    sim.read()
    assert np.allclose(sim.time, nstep * sim.dt)
    assert np.isfinite(sim.state).all()
    assert not sim.status.any()


def test_models_load_by_name_from_any_directory(tmp_path):
    out = subprocess.run(
        [sys.executable, "-c", "import batchsim; print(batchsim.make('quadruped', 2).nworld)"],
        cwd=tmp_path, capture_output=True, text=True, check=True,
    )
    assert out.stdout.strip() == "2"


def test_ros2_plugin_block_is_read_and_stripped():
    spec = batchsim.load("car")
    assert spec.ros is not None
    assert spec.ros.ros_namespace == "car/"
    assert spec.ros.topic_queue_size == 10
    assert spec.ros.topic_reliability == "reliable"
    assert "mujoco.ros2" not in spec.xml


PLUGIN_MJCF = """<mujoco model="one">
  <extension>
    <plugin plugin="mujoco.ros2">
      <instance name="bridge">
        <config key="ros_namespace" value="robot/"/>
        <config key="topic_queue_size" value="3"/>
        <config key="topic_reliability" value="best_effort"/>
      </instance>
    </plugin>
  </extension>
  <worldbody><body><joint name="j" type="slide"/><geom size=".1"/></body></worldbody>
  <actuator><velocity name="v" joint="j" kv="10"/></actuator>
  <sensor><jointpos name="p" joint="j"/></sensor>
</mujoco>"""


def test_any_mjcf_written_for_the_plugin_loads(tmp_path):
    path = tmp_path / "one.xml"
    path.write_text(PLUGIN_MJCF)
    spec = batchsim.load(path)
    assert spec.ros.ros_namespace == "robot/" and spec.ros.topic_queue_size == 3
    assert spec.ros.topic_reliability == "best_effort"
    assert spec.command_interfaces == ["j/velocity"]


def test_unknown_plugin_key_is_named(tmp_path):
    path = tmp_path / "bad.xml"
    path.write_text(PLUGIN_MJCF.replace("topic_queue_size", "queue"))
    with pytest.raises(ModelError, match="unknown mujoco.ros2 config key 'queue'"):
        batchsim.load(path)


def test_relative_assets_still_resolve_after_stripping(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "body.xml").write_text(
        '<mujoco><worldbody><body><joint name="j"/><geom size=".1"/></body></worldbody></mujoco>'
    )
    main = PLUGIN_MJCF.replace(
        '<worldbody><body><joint name="j" type="slide"/><geom size=".1"/></body></worldbody>',
        '<include file="parts/body.xml"/>',
    ).replace('<velocity name="v" joint="j" kv="10"/>', '<motor name="m" joint="j"/>').replace(
        '<jointpos name="p" joint="j"/>', ""
    )
    (tmp_path / "robot.xml").write_text(main)
    spec = batchsim.load(tmp_path / "robot.xml")
    assert spec.command_interfaces == ["j/effort"]


def test_an_mjcf_that_includes_itself_is_one_line_naming_the_loop(tmp_path):
    """Before, a RecursionError traceback (issue 47's review)."""
    body = '<worldbody><body><joint/><geom size=".1"/></body></worldbody>'
    (tmp_path / "self.xml").write_text(f'<mujoco><include file="self.xml"/>{body}</mujoco>')
    with pytest.raises(ModelError, match=r"self.xml: its includes loop: self.xml -> self.xml \(a file"):
        batchsim.load(tmp_path / "self.xml")
    (tmp_path / "parts").mkdir()
    (tmp_path / "a.xml").write_text(f'<mujoco><include file="parts/b.xml"/>{body}</mujoco>')
    (tmp_path / "parts" / "b.xml").write_text('<mujoco><include file="a.xml"/></mujoco>')  # includes resolve from the top file's folder
    with pytest.raises(ModelError, match=r"a.xml: its includes loop: a.xml -> b.xml -> a.xml"):
        batchsim.load(tmp_path / "a.xml")


ROS2_CONTROL = """<robot name="arm">
  <ros2_control name="arm" type="system">
    <hardware><plugin>batchsim/BatchedSystem</plugin></hardware>
    <joint name="joint1">
      <command_interface name="position"/>
      <state_interface name="position"><param name="initial_value">0.3</param></state_interface>
      <state_interface name="velocity"/>
    </joint>
    <joint name="joint2">
      <command_interface name="position"/>
      <state_interface name="position"/>
    </joint>
    <sensor name="wrist_force">
      <state_interface name="force.x"/>
    </sensor>
  </ros2_control>
</robot>"""


def test_ros2_control_block_narrows_the_interfaces(tmp_path):
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(ROS2_CONTROL)
    sim = batchsim.make("arm", 2, "cpu", ros2_control=urdf)
    assert sim.export_command_interfaces() == ["joint1/position", "joint2/position"]
    assert sim.export_state_interfaces() == [
        "joint1/position", "joint1/velocity", "joint2/position",
        "wrist_force/force.x", "wrist_force/force.y", "wrist_force/force.z",
    ]
    sim.configure()
    sim.read()
    # initial_value is where the joint starts, and the command holds it
    assert np.allclose(sim.state[:, 0], 0.3)
    assert np.allclose(sim.command[:, 0], 0.3)


def test_initial_value_sets_where_the_joint_starts_not_its_kinematic_zero():
    """initial_value is the initial qpos (as mujoco_ros2_control sets it), never qpos0: the
    world then moves exactly as plain MuJoCo started at that qpos, under the same commands."""
    import mujoco

    sim = batchsim.make("arm", 2, "cpu", ros2_control=ROS2_CONTROL)
    m = sim.model
    plain = mujoco.MjModel.from_xml_path(str(batchsim.model.model_path("arm")))
    np.testing.assert_array_equal(m.qpos0, plain.qpos0)  # the kinematic zero is untouched
    sim.configure()
    sim.activate()
    d = mujoco.MjData(plain)
    d.qpos[plain.joint("joint1").qposadr[0]] = 0.3
    d.ctrl[plain.actuator("joint1").id] = 0.3  # the initial command holds the initial value
    sim.command[:, 1] = d.ctrl[plain.actuator("joint2").id] = -0.4
    for _ in range(3):
        sim.write()
        sim.step(100)
        for _ in range(100):
            mujoco.mj_step(plain, d)
    sim.read()
    np.testing.assert_array_equal(sim.state[0, [0, 2]], d.qpos[[0, 1]])  # bit for bit
    sim.reset(worlds=[1])  # reset returns to the initial value; world 0 stays where it went
    assert sim.state[1, 0] == 0.3 and sim.state[1, 2] == 0.0 and sim.state[0, 2] < -0.3


def test_ros2_control_block_given_as_text():
    sim = batchsim.make("arm", 1, "cpu", ros2_control=ROS2_CONTROL)
    assert sim.export_command_interfaces() == ["joint1/position", "joint2/position"]


def test_inline_ros2_control_block_in_the_mjcf(tmp_path):
    text = Path(batchsim.model.model_path("arm")).read_text()
    block = ROS2_CONTROL.split("\n", 1)[1].rsplit("</robot>", 1)[0]
    path = tmp_path / "arm.xml"
    path.write_text(text.replace("</mujoco>", block + "</mujoco>"))
    sim = batchsim.make(path, 1, "cpu")
    assert sim.export_command_interfaces() == ["joint1/position", "joint2/position"]


def test_command_interface_no_actuator_serves_fails_at_configure():
    block = ROS2_CONTROL.replace(
        '<joint name="joint2">\n      <command_interface name="position"/>',
        '<joint name="joint2">\n      <command_interface name="velocity"/>',
    )
    sim = batchsim.make("arm", 1, "cpu", ros2_control=block)
    with pytest.raises(ConfigurationError, match=r"joint 'joint2'.*joint2/velocity"):
        sim.configure()
    assert sim.lifecycle_state is S.UNCONFIGURED


def test_unknown_joint_in_ros2_control_fails_at_configure():
    sim = batchsim.make("arm", 1, "cpu", ros2_control=ROS2_CONTROL.replace('"joint2"', '"joint9"'))
    with pytest.raises(ConfigurationError, match="joint 'joint9'"):
        sim.configure()


@pytest.mark.parametrize(
    "text, message",
    [
        ("<mujoco><worldbody><body></worldbody></mujoco>", r"bad.xml:1:\d+: malformed XML: mismatched tag"),
        ("<mujoco><worldbody><bogus/></worldbody></mujoco>", r"bad.xml: XML Error: .*'bogus', line 1"),
        ("<robot/>", r"a URDF: give it as a .urdf or .xacro file, which batchsim compiles to MJCF"),
    ],
)
def test_bad_mjcf_is_one_clear_line(tmp_path, text, message):
    path = tmp_path / "bad.xml"
    path.write_text(text)
    with pytest.raises(ModelError, match=message) as e:
        batchsim.load(path)
    assert "\n" not in str(e.value)


def test_unknown_model_name_lists_the_shipped_ones():
    with pytest.raises(ModelError, match=r"unknown model 'armm'.*arm, car, humanoid, quadruped"):
        batchsim.load("armm")


def test_missing_file():
    with pytest.raises(ModelError, match="no such file"):
        batchsim.load("/nonexistent/robot.xml")


def test_unknown_backend_and_option():
    with pytest.raises(ValueError, match="unknown backend 'gpu'"):
        batchsim.make("arm", 1, "gpu")
    with pytest.raises(ValueError, match="unknown option 'threads' for backend cpu"):
        batchsim.make("arm", 1, "cpu", threads=2)


_PACKAGE = {"cpu": "mujoco", "mjx": "jax", "warp": "mujoco_warp"}


@pytest.mark.parametrize(
    "backend, option, value, must",
    [
        ("cpu", "nthread", "four", "an integer"),
        ("cpu", "nthread", 2.5, "an integer"),
        ("cpu", "nthread", True, "an integer"),
        ("cpu", "nthread", -1, ">= 0"),
        ("cpu", "deterministic", "yes", "a bool"),
        ("mjx", "deterministic", 1, "a bool"),
        ("warp", "nconmax", "many", "an integer"),
        ("warp", "njmax", -5, ">= 0"),
        ("warp", "max_data_bytes", "2G", "a number"),
        ("warp", "max_data_bytes", 0, ">= 1"),
        ("warp", "max_data_bytes", float("nan"), ">= 1"),
        ("warp", "graph", "no", "a bool"),
    ],
)
def test_a_backend_option_of_the_wrong_type_or_range_is_named_at_make(backend, option, value, must):
    """Issue 42: options were checked by name only; nthread="four" failed at configure with
    "invalid literal for int()", naming no option. make() names it, its backend and the value."""
    need(_PACKAGE[backend])
    with pytest.raises(ValueError) as e:
        batchsim.make("arm", 1, backend, **{option: value})
    assert str(e.value) == f"option {option} of backend {backend} must be {must}, got {value!r}"


@pytest.mark.parametrize(
    "backend, options",
    [
        ("cpu", {"nthread": np.int64(2), "deterministic": np.True_}),
        ("mjx", {"device": "cpu", "deterministic": True}),
        ("warp", {"nconmax": None, "njmax": 64, "max_data_bytes": 2e9, "device": "cpu", "graph": False}),
    ],
)
def test_backend_options_of_the_right_types_are_taken(backend, options):
    """What the checks let through: NumPy's scalars, None where the default is None, a device by name."""
    need(_PACKAGE[backend])
    sim = batchsim.make("arm", 1, backend, **options)
    assert {k: sim.options[k] for k in options} == options


@pytest.mark.parametrize("backend", list(_PACKAGE))
def test_every_option_whose_default_is_none_declares_its_type(backend):
    """None says nothing of what else an option takes: each such option of a shipped backend
    says it (OPTION_TYPES), so that make() checks it too."""
    need(_PACKAGE[backend])
    cls = batchsim.backends.backend_class(batchsim.backends.parse(backend))
    undeclared = [o for o, default in cls.OPTIONS.items() if default is None and o not in cls.OPTION_TYPES]
    assert not undeclared, f"the {backend} backend declares no type for {undeclared}"


# ---------------------------------------------------------------- the command


def batchsim_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, "-m", "batchsim.cli", *args], capture_output=True, text=True, timeout=timeout, env=env
    )


@pytest.mark.parametrize(
    "args, message",
    [
        (["--model", "nope", "--no-ros"], "unknown model 'nope'"),
        (["--model", "/no/such.xml", "--no-ros"], "no such file"),
        (["--wrolds", "3"], "unrecognized arguments: --wrolds"),
        (["--worlds", "0", "--no-ros"], "--worlds must be >= 1"),
        (["--backend", "gpu", "--no-ros"], "unknown backend 'gpu'"),
        (["info", "nope"], "unknown model 'nope'"),
    ],
)
def test_cli_errors_are_one_line_and_exit_2(args, message):
    out = batchsim_cli(*args)
    assert out.returncode == 2, out.stderr
    assert message in out.stderr
    assert "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_cli_runs_for_a_duration_and_reports(tmp_path):
    out = batchsim_cli(
        "--worlds", "4", "--duration", "3", "--rtf", "2", "--no-ros", "--backend", "cpu", "--deterministic"
    )
    assert out.returncode == 0, out.stderr
    assert "4 x arm on cpu" in out.stderr
    assert "rtf" in out.stderr and "steps/s" in out.stderr and "diverged 0/4" in out.stderr
    assert "stopped at sim time 3.000" in out.stderr


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_cli_sigterm_and_sigint_exit_cleanly():
    """Once the run has begun (its first line printed), a signal ends it cleanly with 0;
    during start-up it exits with 130/143 (tests/test_cli.py)."""
    import signal

    for sig in (signal.SIGTERM, signal.SIGINT):
        proc = subprocess.Popen(
            [sys.executable, "-m", "batchsim.cli", "--worlds", "2", "--no-ros"],
            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        seen = []
        for line in proc.stderr:  # the loop runs once the first status line is out
            seen.append(line)
            if "steps/s" in line:
                break
        assert proc.poll() is None, "".join(seen)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, "".join(seen) + err
        assert "Traceback" not in "".join(seen) + err


def test_cli_info_lists_interfaces_and_sensors():
    out = batchsim_cli("info", "quadruped")
    assert out.returncode == 0, out.stderr
    assert "FL_knee/effort" in out.stdout
    assert "imu_orientation" in out.stdout and "framequat" in out.stdout
    assert "backend" in out.stdout


def test_auto_ignores_options_of_backends_it_did_not_pick_and_says_so(monkeypatch):
    monkeypatch.setattr(batchsim.backends, "cuda_gpu", lambda: False)
    sim = batchsim.make("arm", 2, "auto", nconmax=50)
    assert sim.name == "cpu"
    assert "ignored nconmax" in sim.reason


def test_cpu_device_arrays_are_the_live_batch_arrays():
    sim = batchsim.make("arm", 2, "cpu")
    sim.configure()
    arrays = sim.device_arrays()
    assert arrays["qpos"].shape == (2, 6) and arrays["ctrl"].shape == (2, 6)
    before = arrays["time"].copy()
    sim.step(3)
    assert np.allclose(arrays["time"], before + 3 * sim.dt)


_PROP_FIRST = """
<mujoco>
  <worldbody>
    <body name="cube" pos="1 0 0.1"><freejoint name="cube_free"/><geom type="box" size=".05 .05 .05"/></body>
    {robot}
  </worldbody>
  <actuator>{actuators}</actuator>
</mujoco>
"""


def test_floating_base_is_the_robots_free_joint_not_a_prop():
    """A free prop listed before the robot is not the base; a fixed-base robot has none."""
    floating = _PROP_FIRST.format(
        robot='<body name="torso" pos="0 0 1"><freejoint name="root"/><geom size=".1"/>'
        '<body name="leg"><joint name="hip" type="hinge"/><geom size=".05"/></body></body>',
        actuators='<motor joint="hip"/>',
    )
    spec = batchsim.model.load_string(floating)
    assert spec.floating_base is not None
    assert (spec.floating_base.joint, spec.floating_base.body) == ("root", "torso")
    assert spec.floating_base.qposadr == 7 and spec.floating_base.dofadr == 6

    fixed = _PROP_FIRST.format(
        robot='<body name="link"><joint name="j" type="hinge"/><geom size=".05"/></body>',
        actuators='<motor joint="j"/>',
    )
    assert batchsim.model.load_string(fixed).floating_base is None


# --- real robots: keyframes, ros2_control blocks as mujoco_ros2_control reads them ---

ROBOT = """<mujoco model="robot">
  <compiler angle="radian"/>
  <option timestep="0.002"><flag contact="disable"/></option>
  <worldbody>
    <body name="link1" pos="0 0 0.5">
      <joint name="j1" axis="0 1 0" range="-3 3" damping="1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="link2" pos="0.3 0 0">
        <joint name="j2" axis="0 1 0" range="-3 3" damping="1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
        <site name="ft" pos="0.3 0 0"/>
        <body name="finger_l" pos="0.3 0.02 0">
          <joint name="finger_left" type="slide" axis="0 1 0" range="0 0.04"/>
          <geom type="box" size="0.01 0.005 0.02" mass="0.05"/>
        </body>
        <body name="finger_r" pos="0.3 -0.02 0">
          <joint name="finger_right" type="slide" axis="0 1 0" range="-0.04 0"/>
          <geom type="box" size="0.01 0.005 0.02" mass="0.05"/>
        </body>
      </body>
    </body>
    <body name="cart" pos="1 0 0.1">
      <joint name="cart_x" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.05" mass="2"/>
      <site name="cart_site"/>
    </body>
  </worldbody>
  <tendon><fixed name="split"><joint joint="finger_left" coef="0.5"/><joint joint="finger_right" coef="-0.5"/></fixed></tendon>
  <actuator>
    <position name="j1_servo" joint="j1" kp="200" kv="10"/>
    <motor name="j2_motor" joint="j2" ctrlrange="-50 50" ctrllimited="true"/>
    <general name="grip" tendon="split" ctrlrange="0 255" ctrllimited="true" biastype="affine" gainprm="0.0784" biasprm="0 -500 -5"/>
    <velocity name="cart_drive" site="cart_site" gear="1 0 0 0 0 0" kv="50"/>
    <motor name="finger_right_motor" joint="finger_right" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
  <sensor>
    <force name="wrist_force" site="ft"/>
    <torque name="wrist_torque" site="ft"/>
    <framequat name="tool_quat" objtype="site" objname="ft"/>
    <framepos name="tool_pos" objtype="site" objname="ft"/>
    <gyro name="tool_gyro" site="ft"/>
    <accelerometer name="tool_accel" site="ft"/>
  </sensor>
  <keyframe>
    <key name="up" qpos="0.3 -0.6 0 0 0"/>
    <key name="home" qpos="0.5 -1.0 0.01 -0.01 0" ctrl="0.5 0 100 0 0"/>
  </keyframe>
</mujoco>"""


def _robot(tmp_path, block: str = "", name: str = "robot.xml", text: str = ROBOT) -> Path:
    path = tmp_path / name
    path.write_text(text.replace("</mujoco>", block + "</mujoco>") if block else text)
    return path


def test_worlds_start_in_the_home_keyframe_and_reset_to_it(tmp_path):
    sim = batchsim.make(_robot(tmp_path), 2, "cpu")
    assert sim.spec.initial.keyframe == "'home'" and sim.spec.keyframes == ["up", "home"]
    sim.configure()
    sim.activate()
    names = sim.export_state_interfaces()
    assert sim.state[0, names.index("j1/position")] == pytest.approx(0.5)
    assert sim.state[0, names.index("j2/position")] == pytest.approx(-1.0)
    # the keyframe gives ctrl: the position servo's command holds it
    assert sim.command[0, sim.export_command_interfaces().index("j1/position")] == pytest.approx(0.5)
    sim.command[:, 0] = 1.5
    sim.write()
    sim.step(200)
    sim.reset(worlds=[1])
    sim.read()
    assert sim.state[1, names.index("j1/position")] == pytest.approx(0.5)
    assert sim.state[0, names.index("j1/position")] != pytest.approx(0.5, abs=0.05)


def test_a_keyframe_is_chosen_by_name_or_index_and_an_unknown_one_is_named(tmp_path):
    path = _robot(tmp_path)
    up = batchsim.load(path, keyframe="up")
    assert up.initial.keyframe == "'up'" and up.initial.qpos[0] == pytest.approx(0.3)
    # no ctrl in the keyframe: the servo holds the joint where it starts, not at ctrl 0
    assert batchsim.model.initial_command(up)[0] == pytest.approx(0.3)
    assert batchsim.load(path, keyframe=0).initial.keyframe == "'up'"
    assert batchsim.load(path, keyframe="1").initial.keyframe == "'home'"
    with pytest.raises(ModelError, match=r"robot.xml: no keyframe 'nope' \(keyframes: 'up', 'home'\)"):
        batchsim.load(path, keyframe="nope")
    plain = batchsim.model.load_string(ROBOT.replace('name="home"', 'name="other"'))
    assert plain.initial.source == "qpos0" and plain.initial.is_qpos0
    assert any("no keyframe 'home'; its keyframes: 'up', 'other' (choose one with --keyframe" in w for w in plain.warnings)


def test_keyframe_flag_and_info_lines(tmp_path):
    from batchsim.cli import main

    path = _robot(tmp_path)
    out = subprocess.run(
        [sys.executable, "-m", "batchsim.cli", "info", str(path), "--keyframe", "up"],
        capture_output=True, text=True, check=True,
    ).stdout
    assert "starts in  keyframe 'up'   (keyframes: 'up', 'home')" in out
    assert main(["info", str(path), "--keyframe", "7"]) == 2


BLOCK = """<ros2_control name="arm" type="system">
  <hardware><plugin>mujoco_ros2_control/MujocoSystemInterface</plugin>{hw}</hardware>
  <joint name="j1"><command_interface name="position"/>
    <state_interface name="position"><param name="initial_value">0.2</param></state_interface>
    <state_interface name="velocity"/><state_interface name="torque"/></joint>
  <joint name="j2"><command_interface name="torque"/><state_interface name="position"/></joint>
  {extra}
</ros2_control>"""


def test_initial_value_sets_a_joint_over_home_but_not_over_a_named_keyframe(tmp_path):
    spec = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra="")))
    assert spec.initial.qpos[0] == pytest.approx(0.2) and spec.initial.qpos[1] == pytest.approx(-1.0)
    assert spec.initial.source == "keyframe 'home' with ros2_control initial_value" and not spec.initial.is_qpos0
    named = batchsim.load(
        _robot(tmp_path, BLOCK.format(hw='<param name="initial_keyframe">up</param>', extra=""))
    )
    assert named.initial.keyframe == "'up'" and named.initial.qpos[0] == pytest.approx(0.3)
    assert any("initial_value of j1: ignored: keyframe 'up'" in w for w in named.warnings)
    bad = batchsim.load(_robot(tmp_path, BLOCK.format(hw='<param name="initial_keyframe">nope</param>', extra="")))
    assert any("initial_keyframe: no keyframe 'nope'" in p for p in bad.problems)


def test_initial_value_over_qpos0_is_where_worlds_start_and_reset_to(tmp_path):
    """Without a keyframe the label says qpos0, but the state is not the model's defaults: the
    start's typed fields (not its label) tell a backend to write it (issue 22)."""
    text = ROBOT.replace('name="home"', 'name="other"')
    spec = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra=""), text=text))
    assert spec.initial.source == "qpos0 with ros2_control initial_value"
    assert spec.initial.keyframe is None and spec.initial.initial_values and not spec.initial.is_qpos0
    sim = batchsim.make(spec, 2, "cpu")
    sim.configure()
    sim.activate()
    column = sim.export_state_interfaces().index("j1/position")
    assert sim.state[:, column] == pytest.approx([0.2, 0.2])
    sim.command[:, 0] = 1.5
    sim.write()
    sim.step(200)
    sim.reset(worlds=[1])
    sim.read()
    assert sim.state[1, column] == pytest.approx(0.2) and sim.state[0, column] != pytest.approx(0.2, abs=0.05)


def test_a_sensors_type_is_mujocos_enum_and_its_name_is_for_display(tmp_path):
    """Sensor.type is mujoco.mjtSensor (issue 22); type_name is what `batchsim info` prints. The
    enum survives pickling (a fleet's shard processes and bridge workers get the spec) equal."""
    spec = batchsim.load(_robot(tmp_path))
    quat = spec.sensor("tool_quat")
    assert quat.type == mujoco.mjtSensor.mjSENS_FRAMEQUAT and quat.type_name == "framequat"
    assert quat.fields == ("orientation.w", "orientation.x", "orientation.y", "orientation.z")
    assert [s.type_name for s in spec.sensors] == ["force", "torque", "framequat", "framepos", "gyro", "accelerometer"]
    assert pickle.loads(pickle.dumps(quat)) == quat


def test_torque_and_force_name_the_effort_interface(tmp_path):
    spec = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra="")))
    assert spec.command_interfaces == ["j1/position", "j2/torque"]
    assert [c.name for c in spec.state][:4] == ["j1/position", "j1/velocity", "j1/torque", "j2/position"]
    assert spec.state[2].source is StateSource.QFRC_ACTUATOR


def test_state_sources_name_the_mjdata_fields_read_gathers(tmp_path):
    """A state column's source is a StateSource whose value names the MjData field read() takes
    it from, in READ_FIELDS' order."""
    assert READ_FIELDS == ("qpos", "qvel", "qfrc_actuator", "sensordata")
    assert [StateSource(f) for f in READ_FIELDS] == list(StateSource)
    spec = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra="")))
    d = mujoco.MjData(spec.mjmodel)
    assert {c.source for c in spec.state} >= {StateSource.QPOS, StateSource.QVEL, StateSource.QFRC_ACTUATOR}
    for c in spec.state:
        assert isinstance(c.source, StateSource) and 0 <= c.index < getattr(d, c.source.value).size, c


def test_tendon_and_site_actuators_match_by_their_name(tmp_path):
    extra = """<joint name="grip"><command_interface name="position"/></joint>
      <joint name="cart_drive"><command_interface name="velocity"/><state_interface name="velocity"/></joint>"""
    spec = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra=extra)))
    assert not spec.problems, spec.problems
    cmds = {c.name: c for c in spec.commands}
    assert cmds["grip/position"].actuator == "grip"
    assert cmds["cart_drive/velocity"].actuator == "cart_drive"
    assert any("'cart_drive'" in w and "state interfaces (velocity) are not available" in w for w in spec.warnings)
    assert any("'grip'" in w and "control units (ctrlrange 0 255)" in w for w in spec.warnings)
    # a controller takes the actuator's name as a joint, as the block does
    from batchsim.controllers import load_controllers

    yaml = "controller_manager:\n  ros__parameters:\n    g:\n      type: position_controllers/JointGroupPositionController\n"
    assert load_controllers(yaml + "g:\n  ros__parameters:\n    joints: [grip]\n", spec, 1)["g"].joints == ["grip"]
    # a tendon actuator named after a joint is that joint's, as mujoco_ros2_control names them
    named = batchsim.model.load_string(ROBOT.replace('name="grip"', 'name="finger_left"'))
    assert "finger_left/position" in named.command_interfaces


def test_a_gripper_in_control_units_is_scaled_to_the_joint_range(tmp_path):
    extra = """<joint name="grip"><command_interface name="position">
      <param name="min">0</param><param name="max">0.04</param></command_interface></joint>"""
    sim = batchsim.make(_robot(tmp_path, BLOCK.format(hw="", extra=extra)), 1, "cpu", keyframe="up")
    cmd = sim.spec.commands[sim.export_command_interfaces().index("grip/position")]
    assert (cmd.scale, cmd.offset) == (pytest.approx(255 / 0.04), 0.0)
    sim.configure()
    sim.activate()
    sim.command[0, 2] = 0.02  # half its range: ctrl 127.5
    sim.write()
    assert sim.device_arrays()["ctrl"][0, 2] == pytest.approx(127.5)


def test_unknown_interfaces_and_actuatorless_commands_are_problems(tmp_path):
    extra = """<joint name="nope"/><joint name="j1b"/>"""
    block = BLOCK.format(hw="", extra=extra).replace('<command_interface name="torque"/>', '<command_interface name="position"/>')
    spec = batchsim.load(_robot(tmp_path, block))
    assert any("'j2': position on effort actuator 'j2_motor' needs PID gains (pid_gains.position.j2" in p for p in spec.problems)
    assert any("'nope': the model has no hinge or slide joint and no actuator of that name" in p for p in spec.problems)
    sim = batchsim.make(spec, 1, "cpu")
    with pytest.raises(ConfigurationError, match="needs PID gains"):
        sim.configure()


def test_what_is_not_understood_is_named_in_a_warning(tmp_path):
    extra = """<transmission name="t"/><gpio name="io"/>
      <joint name="j2b"><param name="foo">1</param></joint>"""
    block = BLOCK.format(hw='<param name="sim_speed_factor">2</param><param name="frobnicate">1</param>', extra=extra)
    spec = batchsim.load(_robot(tmp_path, block))
    text = "\n".join(spec.warnings)
    assert "hardware param 'frobnicate': ignored" in text and "sim_speed_factor" not in text
    assert "gpio 'io': ignored" in text
    # a transmission is run now; one with no plugin is a problem, named
    assert any("transmission 't': plugin '' is not one batchsim runs" in p for p in spec.problems)


def test_several_blocks_are_one_description(tmp_path):
    second = """<ros2_control name="gripper" type="system"><hardware><plugin>x</plugin></hardware>
      <joint name="grip"><command_interface name="position"/></joint></ros2_control>"""
    spec = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra="") + second))
    assert spec.command_interfaces == ["j1/position", "j2/torque", "grip/position"]
    twice = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra="") + second.replace("grip", "j1")))
    assert any("'j1': listed in two blocks" in p for p in twice.problems)


def test_mujoco_type_sensors_read_the_mjcf_sensors_they_name(tmp_path):
    extra = """<sensor name="wrist"><param name="mujoco_type">fts</param>
        <state_interface name="force.x"/><state_interface name="force.z"/><state_interface name="torque.y"/></sensor>
      <sensor name="imu"><param name="mujoco_type">imu</param><param name="mujoco_sensor_name">tool</param>
        <param name="angular_velocity_mjcf_suffix">_gyro</param></sensor>
      <sensor name="tool_pose"><param name="mujoco_type">pose</param><param name="mujoco_sensor_name">tool</param></sensor>"""
    sim = batchsim.make(_robot(tmp_path, BLOCK.format(hw="", extra=extra)), 1, "cpu")
    assert not sim.spec.problems, sim.spec.problems
    names = sim.export_state_interfaces()
    assert [n for n in names if n.startswith("wrist/")] == ["wrist/force.x", "wrist/force.z", "wrist/torque.y"]
    assert "imu/orientation.w" in names and "imu/linear_acceleration.z" in names
    assert "tool_pose/position.x" in names and "tool_pose/orientation.x" in names
    sim.configure()
    sim.activate()
    sim.step(10)
    sim.read()
    import mujoco

    m, d = sim.model, mujoco.MjData(sim.model)
    # reference: the same state through mj_forward
    d.qpos[:] = sim.device_arrays()["qpos"][0]
    d.qvel[:] = sim.device_arrays()["qvel"][0]
    d.ctrl[:] = sim.device_arrays()["ctrl"][0]
    d.qacc_warmstart[:] = 0
    force = sim.sensordata if False else None  # noqa: F841 - documented below
    raw = sim.device_arrays()["sensordata"][0]
    fz = m.sensor("wrist_force").adr[0] + 2
    assert sim.state[0, names.index("wrist/force.z")] == pytest.approx(-raw[fz])  # read negated, as upstream
    quat = m.sensor("tool_quat").adr[0]
    assert sim.state[0, names.index("imu/orientation.w")] == pytest.approx(raw[quat])
    assert sim.state[0, names.index("imu/orientation.x")] == pytest.approx(raw[quat + 1])
    missing = batchsim.load(_robot(tmp_path, BLOCK.format(hw="", extra=extra.replace("mujoco_sensor_name\">tool<", "mujoco_sensor_name\">tip<"))))
    assert any("no framequat sensor 'tip_quat'" in p for p in missing.problems)


def test_a_mimic_joints_actuator_follows_the_joint_it_mimics(tmp_path):
    extra = """<joint name="finger_left"><command_interface name="effort"/><state_interface name="position"/></joint>"""
    robot = ROBOT.replace('<general name="grip"', '<motor name="finger_left_motor" joint="finger_left" ctrlrange="-1 1"/><general name="grip"')
    mimic = """<joint name="finger_right"><param name="mimic">finger_left</param><param name="multiplier">-1</param>
      <state_interface name="position"/></joint>"""
    sim = batchsim.make(_robot(tmp_path, BLOCK.format(hw="", extra=extra + mimic), text=robot), 1, "cpu")
    assert [(m.joint, m.source, m.actuator, m.multiplier) for m in sim.spec.mimics] == [
        ("finger_right", "finger_left/effort", "finger_right_motor", -1.0)
    ]
    sim.configure()
    sim.activate()
    sim.command[0, sim.export_command_interfaces().index("finger_left/effort")] = 0.5
    sim.write()
    ctrl = sim.device_arrays()["ctrl"][0]
    assert ctrl[sim.model.actuator("finger_right_motor").id] == pytest.approx(-0.5)


MESH = "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def test_an_inline_block_in_a_scene_that_includes_a_robot_with_its_own_meshdir_loads_anywhere(tmp_path):
    (tmp_path / "assets").mkdir()
    (tmp_path / "assets" / "tip.obj").write_text(MESH)
    robot = ROBOT.replace('<compiler angle="radian"/>', '<compiler angle="radian" meshdir="assets"/><asset><mesh file="tip.obj"/></asset>').replace(
        '<site name="ft"', '<geom type="mesh" mesh="tip" contype="0" conaffinity="0" mass="0"/><site name="ft"'
    )
    (tmp_path / "robot.xml").write_text(robot)
    scene = tmp_path / "scene.xml"
    scene.write_text(
        '<mujoco model="scene"><include file="robot.xml"/>'
        + BLOCK.format(hw="", extra="")
        + '<worldbody><geom type="plane" size="2 2 .1"/></worldbody></mujoco>'
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = subprocess.run(
        [sys.executable, "-c", f"import batchsim; s = batchsim.load({str(scene)!r}); print(s.command_interfaces, s.initial.keyframe)"],
        cwd=elsewhere, capture_output=True, text=True,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "['j1/position', 'j2/torque'] 'home'"


PIDS = """/**:
  ros__parameters:
    pid_gains:
      position:
        j2: {p: 40.0, i: 60.0, d: 1.5, u_clamp_max: 50.0, u_clamp_min: -50.0}
    pid_gains:
      velocity:
        j2: {p: 1.0, i: 10.0, d: 0.0}
"""


def _pid_block(tmp_path) -> str:
    (tmp_path / "pids.yaml").write_text(PIDS)
    return BLOCK.format(hw='<param name="pids_config_file">pids.yaml</param>', extra="").replace(
        '<command_interface name="torque"/>', '<command_interface name="position"/><command_interface name="velocity"/>'
    )


@pytest.mark.parametrize(
    "backend, shards",
    [("cpu", None), ("warp", "threads"), ("warp", "processes")],
    ids=["cpu", "warp-2dev", "warp-2proc"],
)
def test_position_and_velocity_on_a_motor_run_through_the_pids_config(tmp_path, backend, shards):
    """Also over two devices: a mode switch reaches every device's actuation (it once stayed
    in the fleet's own, and the shards went on driving position)."""
    devices = {} if shards is None else {"devices": ["cpu", "cpu"]}
    if shards == "processes":
        devices["processes"] = True
    sim = batchsim.make(_robot(tmp_path, _pid_block(tmp_path)), 2, backend, **devices)
    cmds = {c.name: c for c in sim.spec.commands}
    # the same file writes pid_gains twice, as mujoco_ros2_control's does: both are read
    assert cmds["j2/position"].pid.p == 40.0 and cmds["j2/velocity"].pid.p == 1.0
    sim.configure()
    sim.activate()
    names = sim.export_state_interfaces()
    col = sim.export_command_interfaces().index("j2/position")
    assert sim.command[0, col] == pytest.approx(-1.0)  # holds the home keyframe
    sim.command[1, col] = -0.4
    for _ in range(300):  # 3 s at 100 Hz
        sim.read()
        sim.write()
        sim.step(5)
    sim.read()
    q = sim.state[:, names.index("j2/position")].copy()
    assert q[0] == pytest.approx(-1.0, abs=0.02) and q[1] == pytest.approx(-0.4, abs=0.02)
    # the velocity interface drives the motor once switched to, as ros2_control switches modes
    sim.perform_command_mode_switch(["j2/velocity"])
    sim.command[:, sim.export_command_interfaces().index("j2/velocity")] = 0.5
    for _ in range(50):  # 0.5 s
        sim.read()
        sim.write()
        sim.step(5)
    sim.read()
    moved = sim.state[:, names.index("j2/position")] - q  # 0.5 s at about 0.5 rad/s; held, it stays
    assert ((moved > 0.15) & (moved < 0.5)).all(), moved


def test_pid_matches_a_plain_reference_loop():
    from batchsim.pid import AntiWindup, PidBank, PidGains

    gains = [
        PidGains(p=3.0, i=2.0, d=0.5, i_clamp_max=0.4, i_clamp_min=-0.4, u_clamp_max=2.0, u_clamp_min=-2.0),
        PidGains(p=1.0, i=4.0, d=0.0, u_clamp_max=1.0, u_clamp_min=-1.0,
                 antiwindup_strategy=AntiWindup.CONDITIONAL_INTEGRATION),
    ]
    bank = PidBank(gains, 3)
    rng = np.random.default_rng(0)
    ref_i = np.zeros((3, 2))
    ref_last = [[None, None] for _ in range(3)]
    for _ in range(40):
        error = rng.normal(size=(3, 2))
        dt = 0.01
        out = bank.update(error, np.full(3, dt))
        for w in range(3):
            for k, g in enumerate(gains):
                e = error[w, k]
                d = 0.0 if ref_last[w][k] is None else g.d * (e - ref_last[w][k]) / dt
                inc = g.i * e * dt
                trial = g.p * e + ref_i[w, k] + d
                if g.antiwindup_strategy is AntiWindup.CONDITIONAL_INTEGRATION and (
                    (trial > g.u_clamp_max and e > 0) or (trial < g.u_clamp_min and e < 0)
                ):
                    inc = 0.0
                ref_i[w, k] = min(max(ref_i[w, k] + inc, g.i_clamp_min), g.i_clamp_max)
                u = min(max(g.p * e + ref_i[w, k] + d, g.u_clamp_min), g.u_clamp_max)
                ref_last[w][k] = e
                assert out[w, k] == pytest.approx(u)


def test_a_bad_command_world_keeps_its_pid_state_clean(tmp_path):
    sim = batchsim.make(_robot(tmp_path, _pid_block(tmp_path)), 2, "cpu")
    sim.configure()
    sim.activate()
    col = sim.export_command_interfaces().index("j2/position")
    sim.read()
    sim.write()
    sim.step(10)
    sim.command[1, col] = np.nan
    sim.read()
    sim.write()
    assert sim.status[1] & batchsim.Status.BAD_COMMAND and not sim.status[0]
    ctrl = sim.device_arrays()["ctrl"]
    assert np.isfinite(ctrl).all()
    sim.command[1, col] = -1.0
    sim.step(10)
    sim.read()
    sim.write()
    assert np.isfinite(sim.device_arrays()["ctrl"]).all() and not sim.status.any()


XACRO = """<?xml version="1.0"?>
<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="robot">
  <xacro:arg name="use_pid" default="false"/>
  <ros2_control name="arm" type="system">
    <hardware>
      <plugin>mujoco_ros2_control/MujocoSystemInterface</plugin>
      <xacro:if value="$(arg use_pid)">
        <param name="pids_config_file">$(find my_robot_description)/config/pids.yaml</param>
      </xacro:if>
    </hardware>
    <joint name="j1"><command_interface name="position"/><state_interface name="position"/></joint>
    <joint name="j2">
      <xacro:if value="$(arg use_pid)"><command_interface name="position"/></xacro:if>
      <xacro:unless value="$(arg use_pid)"><command_interface name="effort"/></xacro:unless>
      <state_interface name="position"/>
    </joint>
  </ros2_control>
</robot>"""


def test_a_xacro_description_is_expanded_with_its_arguments(tmp_path):
    pkg = tmp_path / "src" / "my_robot_description"
    (pkg / "urdf").mkdir(parents=True)
    (pkg / "config").mkdir()
    (pkg / "config" / "pids.yaml").write_text(PIDS)
    (pkg / "urdf" / "robot.urdf.xacro").write_text(XACRO)
    model = _robot(tmp_path)
    plain = batchsim.load(model, ros2_control=pkg / "urdf" / "robot.urdf.xacro")
    assert plain.command_interfaces == ["j1/position", "j2/effort"] and not plain.problems
    with_pid = batchsim.load(model, ros2_control=f"{pkg / 'urdf' / 'robot.urdf.xacro'} use_pid:=true")
    assert with_pid.command_interfaces == ["j1/position", "j2/position"] and not with_pid.problems
    assert with_pid.commands[1].pid.p == 40.0  # $(find my_robot_description): the folder above the file
    with pytest.raises(ModelError, match="xacro argument 'use_pid' is not key:=value"):
        batchsim.load(model, ros2_control=f"{pkg / 'urdf' / 'robot.urdf.xacro'} use_pid")
    (pkg / "urdf" / "broken.urdf.xacro").write_text(XACRO.replace("$(arg use_pid)", "$(arg nope)"))
    with pytest.raises(ModelError, match="broken.urdf.xacro: xacro: .*nope"):
        batchsim.load(model, ros2_control=pkg / "urdf" / "broken.urdf.xacro")


def test_odom_free_joint_name_picks_the_floating_base(tmp_path):
    scene = ROBOT.replace('<body name="cart" pos="1 0 0.1">\n      <joint name="cart_x" type="slide" axis="1 0 0"/>',
                          '<body name="cart" pos="1 0 0.1">\n      <freejoint name="floating_base_joint"/>')
    scene = scene.replace("0 0 0 0\"/>", "0 0 0 0 0 0 0 0\"/>").replace('qpos="0.5 -1.0 0.01 -0.01 0"', 'qpos="0.5 -1.0 0.01 -0.01 1 0 0.1 1 0 0 0"')
    scene = scene.replace('qpos="0.3 -0.6 0 0 0"', 'qpos="0.3 -0.6 0 0 1 0 0.1 1 0 0 0"')
    block = BLOCK.format(hw='<param name="odom_free_joint_name">floating_base_joint</param>', extra="")
    spec = batchsim.load(_robot(tmp_path, block, text=scene))
    assert spec.floating_base is not None and spec.floating_base.body == "cart"


def test_auto_picks_warp_from_the_measured_crossover_on_a_gpu(monkeypatch):
    """The held-out run on an H200 (RESULTS.md): warp beats cpu at 256 humanoids, cpu wins at 128."""
    need("mujoco_warp")
    monkeypatch.setattr(batchsim.backends, "cuda_gpu", lambda: True)
    spec = batchsim.load("humanoid")
    assert batchsim.backends.resolve("auto", spec, 128)[0] is batchsim.Backend.CPU
    assert batchsim.backends.resolve("auto", spec, 256)[0] is batchsim.Backend.WARP


def test_install_hints_name_the_checkout_not_a_package_index(monkeypatch):
    """batchsim is not on a package index: a missing backend's hint installs from the checkout."""
    real = batchsim.backends.importlib.import_module

    def missing_warp(name: str):
        if name == "batchsim.backends.warp":
            raise ModuleNotFoundError("No module named 'mujoco_warp'", name="mujoco_warp")
        return real(name)

    monkeypatch.setattr(batchsim.backends.importlib, "import_module", missing_warp)
    with pytest.raises(batchsim.BackendUnavailable, match=r"pip install -e '.*\[warp\]'"):
        batchsim.backends.backend_class(batchsim.Backend.WARP)
