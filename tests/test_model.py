"""Model loading: shipped models by name, MJCF extension and ros2_control blocks, errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import batchsim
from batchsim import ConfigurationError, LifecycleState, ModelError

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
        ("<robot/>", r"not an MJCF file \(root element <robot>"),
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


def test_cli_sigterm_and_sigint_exit_cleanly():
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
