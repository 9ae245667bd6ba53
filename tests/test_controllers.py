"""ros2_control-style controllers: the issue's behaviours in-process, through the contract.

The controllers' own inputs (set_trajectory, set_cmd_vel, set_commands) are what the ROS
bridge calls with each message; the test marked `ros` sends a real JointTrajectory to a
`batchsim` process.
"""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

import batchsim
from batchsim.controllers import (
    CONTROLLER_TYPES,
    Controller,
    ControllerManager,
    Params,
    TrajectoryBatch,
    default_controllers,
    load_controllers,
)
from batchsim.loop import SimLoop
from batchsim.model import InterfaceKind
from batchsim.types import ConfigurationError

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]


def running(model: str, nworld: int, yaml_source=None):
    sim = batchsim.make(model, nworld, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    manager = load_controllers(yaml_source or default_controllers(model), sim.spec, nworld)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    return sim, manager, loop


def run_until(loop: SimLoop, t: float) -> None:
    while loop.sim_time < t - 1e-9:
        loop.run_period()


# ---------------------------------------------------------------- the scenarios


def test_trajectory_to_world_5_of_8_is_followed_and_the_others_hold_still():
    sim, manager, loop = running("arm", 8)
    jtc = manager["joint_trajectory_controller"]
    loop.run_period()
    pos_cols = [sim.export_state_interfaces().index(f"{j}/position") for j in ARM_JOINTS]
    start = sim.state[:, pos_cols].copy()
    goal = np.array([0.5, -0.4, 0.6, 0.3, -0.5, 0.8])
    # a cubic trajectory (velocities given), joints in a different order than the controller's
    order = [5, 0, 3, 1, 4, 2]
    t_now = loop.sim_time
    jtc.set_trajectory(
        5,
        [ARM_JOINTS[k] for k in order],
        [1.0, 2.0],
        [goal[order] / 2, goal[order]],
        [goal[order] / 2, np.zeros(6)],
    )
    run_until(loop, t_now + 1.0)
    assert jtc.executing[5] and not jtc.executing[np.arange(8) != 5].any()
    # half way: the reference is the middle point, and the arm is near it
    np.testing.assert_allclose(jtc.reference_position[5], goal / 2, atol=0.02)
    run_until(loop, t_now + 3.0)
    assert not jtc.executing.any()
    np.testing.assert_allclose(jtc.reference_position[5], goal, atol=1e-12)  # holds the last point
    # tolerance: the position servos (kp 30..200) sag under gravity by up to ~0.03 rad
    tolerance = 0.04
    np.testing.assert_allclose(sim.state[5, pos_cols], goal, atol=tolerance)
    others = np.arange(8) != 5
    np.testing.assert_allclose(sim.state[others][:, pos_cols], start[others], atol=1e-9)


def test_car_cmd_vel_for_2_s_moves_about_1_m_and_odometry_agrees():
    sim, manager, loop = running("car", 3)
    dd = manager["diff_drive_controller"]
    sim.read()
    start = sim.base_state[:, :2].copy()  # the floating base's x, y: the simulated base position
    while loop.sim_time < 2.0 - 1e-9:
        dd.set_cmd_vel(0, 0.5, 0.0)
        dd.set_cmd_vel(1, 0.5, 0.0)  # world 2 gets nothing and stays put
        loop.run_period()
    sim.read()
    moved = np.linalg.norm(sim.base_state[:, :2] - start, axis=1)
    # from standstill through a wheel-velocity loop on torque motors: 0.9 .. 1.0 m
    assert 0.9 < moved[0] < 1.02, moved
    odom = np.linalg.norm(dd.odom_pose[:, :2], axis=1)
    assert abs(odom[0] - moved[0]) < 0.05 * moved[0], (odom, moved)
    assert moved[1] == pytest.approx(moved[0], abs=1e-9)  # worlds are independent and equal
    assert moved[2] < 1e-3 and odom[2] < 1e-3
    assert dd.odom_twist[0, 0] == pytest.approx(0.5, abs=0.05)
    # cmd_vel_timeout (0.5 s): silence stops the wheels
    run_until(loop, 3.5)
    assert abs(dd.command_velocity[0, 0]) < 1e-12
    assert abs(sim.state[0, sim.export_state_interfaces().index("left_wheel_joint/velocity")]) < 0.5


DOCS_STYLE = """\
# in the style of the ros2_control documentation's examples (ros2_control_demos)
controller_manager:
  ros__parameters:
    update_rate: 100  # Hz

    joint_state_broadcaster:
      type: joint_state_broadcaster/JointStateBroadcaster

    forward_position_controller:
      type: forward_command_controller/ForwardCommandController

    joint_trajectory_controller:
      type: joint_trajectory_controller/JointTrajectoryController

    ft_sensor_broadcaster:
      type: force_torque_sensor_broadcaster/ForceTorqueSensorBroadcaster

forward_position_controller:
  ros__parameters:
    joints:
      - joint1
      - joint2
    interface_name: position

joint_trajectory_controller:
  ros__parameters:
    joints:
      - joint3
      - joint4
      - joint5
      - joint6
    command_interfaces:
      - position
    state_interfaces:
      - position
      - velocity
    state_publish_rate: 50.0 # Defaults to 50
    action_monitor_rate: 20.0 # Defaults to 20
    allow_partial_joints_goal: false # Defaults to false
    open_loop_control: true
    allow_integration_in_goal_trajectories: true
    constraints:
      stopped_velocity_tolerance: 0.01 # Defaults to 0.01
      goal_time: 0.0 # Defaults to 0.0 (start immediately)

ft_sensor_broadcaster:
  ros__parameters:
    interface_names.force.x: wrist_force/force.x
    interface_names.force.y: wrist_force/force.y
    interface_names.force.z: wrist_force/force.z
    interface_names.torque.x: wrist_torque/torque.x
    interface_names.torque.y: wrist_torque/torque.y
    interface_names.torque.z: wrist_torque/torque.z
    frame_id: wrist
"""

DIFFBOT_STYLE = """\
/**/controller_manager:
  ros__parameters:
    update_rate: 50
    joint_state_broadcaster:
      type: joint_state_broadcaster/JointStateBroadcaster
    diffbot_base_controller:
      type: diff_drive_controller/DiffDriveController

/**/diffbot_base_controller:
  ros__parameters:
    left_wheel_names: ["left_wheel_joint"]
    right_wheel_names: ["right_wheel_joint"]
    wheel_separation: 0.30
    wheel_radius: 0.06
    wheel_separation_multiplier: 1.0
    left_wheel_radius_multiplier: 1.0
    right_wheel_radius_multiplier: 1.0
    publish_rate: 50.0
    odom_frame_id: odom
    base_frame_id: base_link
    pose_covariance_diagonal : [0.001, 0.001, 0.0, 0.0, 0.0, 0.01]
    twist_covariance_diagonal: [0.001, 0.0, 0.0, 0.0, 0.0, 0.01]
    open_loop: false
    enable_odom_tf: true
    cmd_vel_timeout: 0.5
    publish_limited_velocity: true
    velocity_rolling_window_size: 10
    linear.x.has_velocity_limits: true
    linear.x.has_acceleration_limits: true
    linear.x.has_jerk_limits: false
    linear.x.max_velocity: 1.0
    linear.x.min_velocity: -1.0
    linear.x.max_acceleration: 1.0
    linear.x.max_jerk: 0.0
    linear.x.min_jerk: 0.0
    angular.z.has_velocity_limits: true
    angular.z.has_acceleration_limits: true
    angular.z.has_jerk_limits: false
    angular.z.max_velocity: 1.0
    angular.z.min_velocity: -1.0
    angular.z.max_acceleration: 1.0
    angular.z.min_acceleration: -1.0
    angular.z.max_jerk: 0.0
    angular.z.min_jerk: 0.0
"""


def test_a_yaml_in_the_style_of_the_ros2_control_docs_loads():
    sim, manager, loop = running("arm", 2, DOCS_STYLE)
    assert manager.update_rate == 100.0
    assert list(manager.controllers) == [
        "joint_state_broadcaster",
        "forward_position_controller",
        "joint_trajectory_controller",
        "ft_sensor_broadcaster",
    ]
    assert manager.warnings == []
    assert manager.claimed == {f"joint{i}/position" for i in range(1, 7)}
    manager["forward_position_controller"].set_commands(1, [0.3, -0.2])
    run_until(loop, 0.5)
    names = sim.export_state_interfaces()
    assert sim.state[1, names.index("joint1/position")] == pytest.approx(0.3, abs=0.02)
    assert sim.state[0, names.index("joint1/position")] == pytest.approx(0.0, abs=1e-9)
    jsb = manager["joint_state_broadcaster"]
    assert jsb.names == ARM_JOINTS
    np.testing.assert_array_equal(
        jsb.position, sim.state[:, [names.index(f"{j}/position") for j in ARM_JOINTS]]
    )
    ft = manager["ft_sensor_broadcaster"]
    np.testing.assert_array_equal(ft.force, sim.sensordata["wrist_force"])
    np.testing.assert_array_equal(ft.torque, sim.sensordata["wrist_torque"])

    car = batchsim.load("car")
    dd = load_controllers(DIFFBOT_STYLE, car, 1)["diffbot_base_controller"]
    assert dd.linear.max_v == 1.0 and dd.angular.min_a == -1.0 and dd.linear.min_a == -1.0


def test_columns_that_step_evenly_are_read_through_a_slice_that_gives_what_the_index_gives():
    """Controllers copy state columns through `batchsim.types.as_slice` (a gather through an index array took
    twice as long at 4096 rows): a slice only where the columns step evenly upward."""
    from batchsim.types import as_slice

    state = np.arange(40.0).reshape(4, 10)
    sliced = ([0, 1, 2], [1, 4, 7], [5])
    for cols in (*sliced, [], [2, 1, 0], [0, 2, 3], [3, 3]):
        index = as_slice(np.array(cols, dtype=np.intp))
        assert isinstance(index, slice) == (cols in sliced), cols
        np.testing.assert_array_equal(state[:, index], state[:, np.array(cols, dtype=np.intp)])


def test_shipped_defaults_and_sensor_broadcasters():
    sim, manager, loop = running("quadruped", 2)
    assert list(manager.controllers) == [
        "joint_state_broadcaster",
        "imu_sensor_broadcaster",
        "effort_controller",
    ]
    run_until(loop, 0.1)
    imu = manager["imu_sensor_broadcaster"]
    w, x, y, z = sim.sensordata["imu_orientation"].T
    np.testing.assert_array_equal(imu.orientation, np.stack([x, y, z, w], axis=1))
    np.testing.assert_array_equal(imu.angular_velocity, sim.sensordata["imu_gyro"])
    np.testing.assert_array_equal(imu.linear_acceleration, sim.sensordata["imu_accel"])
    for model in ("arm", "car"):
        assert load_controllers(default_controllers(model), batchsim.load(model), 1).warnings == []


# ---------------------------------------------------------------- bad configuration

HEAD = """\
controller_manager:
  ros__parameters:
    update_rate: 100
"""


def arm_yaml(controllers: str, params: str = "") -> str:
    return HEAD + textwrap.indent(textwrap.dedent(controllers), "    ") + textwrap.dedent(params)


BAD = {
    "unknown type": (
        arm_yaml("c:\n  type: fancy_controllers/Fancy\n"),
        ["controller 'c'", "type", "fancy_controllers/Fancy", *CONTROLLER_TYPES],
    ),
    "missing type": (arm_yaml("c:\n  joints: [joint1]\n"), ["controller 'c'", "type: missing"]),
    # issue 47's review: a type that is a list was a TypeError traceback (unhashable type)
    "type not a name": (arm_yaml("c:\n  type: [a, b]\n"), ["controller 'c'", "type: must be a plugin name, got ['a', 'b']"]),
    "unknown joint": (
        arm_yaml(
            "c:\n  type: position_controllers/JointGroupPositionController\n",
            "c:\n  ros__parameters:\n    joints: [joint1, joint9]\n",
        ),
        ["controller 'c'", "joints", "the model has no joint 'joint9'"],
    ),
    "interface the model lacks": (
        arm_yaml(
            "c:\n  type: forward_command_controller/ForwardCommandController\n",
            "c:\n  ros__parameters:\n    joints: [joint1]\n    interface_name: velocity\n",
        ),
        ["controller 'c'", "interface_name", "'joint1/velocity'", "joint1 has: position"],
    ),
    "state interface the model lacks": (
        arm_yaml(
            "t:\n  type: joint_trajectory_controller/JointTrajectoryController\n",
            "t:\n  ros__parameters:\n    joints: [joint1]\n    command_interfaces: [position]\n"
            "    state_interfaces: [position, velocity, acceleration]\n",
        ),
        ["controller 't'", "state_interfaces", "'joint1/acceleration'"],
    ),
    "missing required parameter": (
        arm_yaml("c:\n  type: position_controllers/JointGroupPositionController\n"),
        ["controller 'c'", "joints: missing"],
    ),
    "unknown sensor": (
        arm_yaml(
            "i:\n  type: imu_sensor_broadcaster/IMUSensorBroadcaster\n",
            "i:\n  ros__parameters:\n    sensor_name: imu\n",
        ),
        ["controller 'i'", "sensor_name", "no IMU sensor 'imu'"],
    ),
    "bad update_rate": (HEAD.replace("100", "-5"), ["controller_manager", "update_rate"]),
    "no controller_manager": ("c:\n  ros__parameters:\n    joints: [joint1]\n", ["controller_manager"]),
    "malformed YAML": (HEAD + "    c: [\n", ["malformed YAML"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_configuration_is_one_line_naming_controller_and_key(case, tmp_path):
    text, expected = BAD[case]
    path = tmp_path / "controllers.yaml"
    path.write_text(text)
    with pytest.raises(ConfigurationError) as info:
        load_controllers(str(path), batchsim.load("arm"), 2)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path))
    for part in expected:
        assert part in message, (part, message)


def test_two_controllers_claiming_one_interface_load_and_the_second_starts_inactive(tmp_path):
    # was a ConfigurationError; ros2_control loads both and activates one
    path = tmp_path / "controllers.yaml"
    path.write_text(
        arm_yaml(
            "a:\n  type: position_controllers/JointGroupPositionController\n"
            "b:\n  type: joint_trajectory_controller/JointTrajectoryController\n",
            "a:\n  ros__parameters:\n    joints: [joint1, joint2]\n"
            "b:\n  ros__parameters:\n    joints: [joint2, joint3]\n    command_interfaces: [position]\n"
            "    state_interfaces: [position]\n",
        )
    )
    manager = load_controllers(str(path), batchsim.load("arm"), 2)
    assert manager.active("a").all() and not manager.active("b").any()
    [line] = [w for w in manager.warnings if "starts inactive" in w]
    for part in ("controller 'b'", "'joint2/position'", "claimed by 'a'", "switch_controller"):
        assert part in line, (part, line)


def test_cli_reports_bad_configuration_before_starting(tmp_path, capsys):
    from batchsim.cli import main

    path = tmp_path / "controllers.yaml"
    path.write_text(BAD["unknown joint"][0])
    assert main(["--worlds", "2", "--no-ros", "--controllers", str(path), "--duration", "0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "joint9" in err[0] and "controller 'c'" in err[0]


def test_cli_runs_with_default_and_no_controllers(capsys):
    from batchsim.cli import main

    for model in ("car", "arm"):
        assert (
            main(
                ["--worlds", "2", "--model", model, "--no-ros", "--rtf", "0", "--duration", "0.05", "--quiet"]
            )
            == 0
        )
    assert (
        main(["--worlds", "2", "--no-ros", "--rtf", "0", "--duration", "0.05", "--controllers", "none"]) == 0
    )
    err = capsys.readouterr().err
    assert "diff_drive_controller" in err and "joint_trajectory_controller" in err


def test_update_rate_sets_the_control_rate(tmp_path):
    from batchsim.cli import run_parser, setup_controllers

    path = tmp_path / "c.yaml"
    path.write_text(
        HEAD.replace("100", "250") + "    jsb:\n      type: joint_state_broadcaster/JointStateBroadcaster\n"
    )
    args = run_parser().parse_args(["--controllers", str(path)])
    sim = batchsim.make("arm", 1, "cpu")
    manager, rate = setup_controllers(sim, args)
    assert rate == 250.0 and list(manager.controllers) == ["jsb"]
    path.write_text(HEAD.replace("100", "300"))  # 3.33 physics steps of 1 ms
    with pytest.raises(ConfigurationError, match="update_rate.*whole number of physics steps"):
        setup_controllers(sim, run_parser().parse_args(["--controllers", str(path)]))


# ---------------------------------------------------------------- trajectory semantics


def test_trajectory_rejections_leave_the_world_unchanged():
    sim, manager, loop = running("arm", 2)
    jtc = manager["joint_trajectory_controller"]
    loop.run_period()
    p = np.zeros((2, 6))
    with pytest.raises(ValueError, match="unknown joint 'joint9'"):
        jtc.set_trajectory(0, [*ARM_JOINTS[:5], "joint9"], [1, 2], p)
    with pytest.raises(ValueError, match="strictly increasing"):
        jtc.set_trajectory(0, ARM_JOINTS, [1, 1], p)
    with pytest.raises(ValueError, match="strictly increasing"):
        jtc.set_trajectory(0, ARM_JOINTS, [2, 1], p)
    with pytest.raises(ValueError, match="lacks joint 'joint6'"):
        jtc.set_trajectory(0, ARM_JOINTS[:5], [1, 2], p[:, :5])
    with pytest.raises(ValueError, match="positions must be 2 points x 6 joints"):
        jtc.set_trajectory(0, ARM_JOINTS, [1, 2], np.zeros((2, 5)))
    with pytest.raises(ValueError, match="finite"):
        jtc.set_trajectory(0, ARM_JOINTS, [1, 2], np.full((2, 6), np.nan))
    with pytest.raises(ValueError, match="out of range"):
        jtc.set_trajectory(2, ARM_JOINTS, [1, 2], p)
    assert not jtc.pending.any()
    run_until(loop, 0.2)
    assert not jtc.executing.any()


def test_a_new_trajectory_replaces_the_old_one_from_its_start_time():
    sim, manager, loop = running("arm", 1)
    jtc = manager["joint_trajectory_controller"]
    loop.run_period()
    a = np.full(6, 0.2)
    jtc.set_trajectory(0, ARM_JOINTS, [2.0], [a])  # linear ramp to 0.2 over 2 s
    run_until(loop, 0.5)
    b = np.full(6, -0.1)
    jtc.set_trajectory(0, ARM_JOINTS, [0.5], [b], start_time=1.0)  # starts at t = 1 s
    run_until(loop, 0.99)
    # still on the first trajectory: ~0.2 * (0.99 - 0.01) / 2
    np.testing.assert_allclose(jtc.reference_position[0], 0.2 * (loop.sim_time - 0.01 - 0.01) / 2, atol=0.004)
    run_until(loop, 1.6)
    np.testing.assert_allclose(jtc.reference_position[0], b)
    # an empty trajectory stops the world where it is
    jtc.set_trajectory(0, ARM_JOINTS, [1.0], [a])
    run_until(loop, 1.8)
    jtc.set_trajectory(0, [], [], np.zeros((0, 0)))
    loop.run_period()
    held = jtc.reference_position[0].copy()
    run_until(loop, 2.5)
    np.testing.assert_array_equal(jtc.reference_position[0], held)


def test_a_single_point_at_time_zero_is_applied_at_once():
    """ros2_controllers samples past a trajectory's end at its last point: one point with
    time_from_start 0 and a zero stamp is the new reference at once, as is a trajectory
    stamped now. Before: neither applied, nor refused, nor counted."""
    sim, manager, loop = running("arm", 2)
    jtc = manager["joint_trajectory_controller"]
    loop.run_period()
    target = np.array([0.3, -0.2, 0.1, 0.0, 0.2, -0.1])
    jtc.set_trajectory(1, ARM_JOINTS, [0.0], [target])
    loop.run_period()
    np.testing.assert_allclose(jtc.reference_position[1], target)
    np.testing.assert_array_equal(jtc.reference_position[0], 0.0)
    run_until(loop, 1.0)
    sim.read()
    names = sim.export_state_interfaces()
    assert abs(sim.state[1, names.index("joint1/position")] - 0.3) < 0.03
    # stamped now, with its only point at time 0: the same
    jtc.set_trajectory(0, ARM_JOINTS, [0.0], [-target], start_time=loop.sim_time)
    loop.run_period()
    np.testing.assert_allclose(jtc.reference_position[0], -target)


class ResetSpy(Controller):
    """A controller that only records the resets it hears of."""

    TYPE = "test/ResetSpy"

    def __init__(self, spec, nworld):
        super().__init__("spy", Params({}, where="test", controller="spy"), spec, nworld)
        self.resets: list[list[int]] = []

    def reset(self, sim, worlds):
        self.resets.append(np.asarray(worlds).tolist())

    def update(self, sim, time, period):
        pass


def test_loop_reset_reaches_every_controller_and_the_reset_world_holds_its_reset_pose():
    sim = batchsim.make("arm", 3, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    loaded = load_controllers(default_controllers("arm"), sim.spec, 3)
    spy = ResetSpy(sim.spec, 3)
    manager = ControllerManager([*loaded, spy], update_rate=loaded.update_rate)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    jtc = manager["joint_trajectory_controller"]
    loop.run_period()
    for w in range(3):
        jtc.set_trajectory(w, ARM_JOINTS, [1.0], [np.full(6, 0.3)])
    run_until(loop, 0.5)
    loop.reset([1])
    # at once, not at the next period: the manager is told, it does not infer it
    assert spy.resets == [[1]] and not jtc.executing[1] and jtc.executing[[0, 2]].all()
    np.testing.assert_array_equal(jtc.reference_position[1], jtc.feedback_position[1])
    run_until(loop, 1.5)
    assert np.abs(jtc.reference_position[1]).max() < 1e-12
    np.testing.assert_allclose(jtc.reference_position[[0, 2]], 0.3)
    loop.reset()
    assert spy.resets == [[1], [0, 1, 2]] and not jtc.executing.any()


def test_loop_reset_by_mask_tells_participants_the_masked_worlds():
    """Issue 42: a (nworld,) bool mask resets the masked worlds, and the participants heard
    the mask as integers ([0 0 1 1]): they get the world indices, as for a list."""

    class Heard:
        def __init__(self):
            self.resets: list[list[int]] = []

        def update(self, sim, time, period):
            pass

        def on_reset(self, sim, worlds):
            self.resets.append(worlds.tolist())

    sim = batchsim.make("arm", 4, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    heard, spy = Heard(), ResetSpy(sim.spec, 4)
    loop = SimLoop(sim, rtf=0, participants=[heard, ControllerManager([spy], update_rate=100.0)])
    loop.reset(np.array([False, False, True, True]))
    loop.reset([1, 3])
    assert heard.resets == [[2, 3], [1, 3]]
    assert spy.resets == [[2, 3], [1, 3]]  # and so the controllers, through the manager
    sim.shutdown()


def test_a_world_whose_time_goes_backwards_is_not_taken_for_reset():
    spec = batchsim.load("arm")
    sim = FakeSim(spec, 2, np.random.default_rng(1))
    manager = load_controllers(default_controllers("arm"), spec, 2)
    jtc = manager["joint_trajectory_controller"]
    manager.update(sim, 0.0, 0.01)
    start = jtc.reference_position.copy()  # open_loop_control: trajectories leave from the reference
    for w in range(2):
        jtc.set_trajectory(w, ARM_JOINTS, [1.0], [np.full(6, 0.3)])  # starts at the next update, 0.01
    for k in range(1, 31):
        sim.advance(0.01)
        manager.update(sim, 0.01 * k, 0.01)
    sim.time[1] = 0.0  # e.g. the cpu backend silently restarting a world's clock
    manager.update(sim, 0.31, 0.01)
    assert jtc.executing.all()
    np.testing.assert_allclose(jtc.reference_position, start + (0.3 - start) * 0.30, atol=1e-12)


# ---------------------------------------------------------------- batched == per world


class FakeSim:
    """The contract's arrays only: state driven by the test, command read back."""

    def __init__(self, spec, nworld, rng):
        self.spec, self.nworld, self.rng = spec, nworld, rng
        self.state = rng.normal(size=(nworld, len(spec.state)))
        self.command = np.zeros((nworld, len(spec.commands)))
        self.time = np.zeros(nworld)

    def advance(self, period):
        self.state += self.rng.normal(scale=0.01, size=self.state.shape)
        self.time += period


def reference_sample(points, mode, t):
    """One world's trajectory at time t, from (time, p, v, a) points: textbook splines."""
    if t >= points[-1][0]:
        return points[-1][1], np.zeros_like(points[-1][1])
    i = max(k for k in range(len(points)) if points[k][0] <= t + 1e-12)
    (ta, p0, v0, a0), (tb, p1, v1, a1) = points[i], points[i + 1]
    T, s = tb - ta, t - ta
    if mode == "linear":
        return p0 + (p1 - p0) * s / T, (p1 - p0) / T
    if mode == "cubic":  # Hermite basis
        u = s / T
        h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
        d00, d10, d01, d11 = (
            (6 * u**2 - 6 * u) / T,
            3 * u**2 - 4 * u + 1,
            (-6 * u**2 + 6 * u) / T,
            3 * u**2 - 2 * u,
        )
        return h00 * p0 + h10 * T * v0 + h01 * p1 + h11 * T * v1, d00 * p0 + d10 * v0 + d01 * p1 + d11 * v1
    # quintic: solve for the coefficients
    M = np.array(
        [
            [1, 0, 0, 0, 0, 0],
            [0, 1, 0, 0, 0, 0],
            [0, 0, 2, 0, 0, 0],
            [1, T, T**2, T**3, T**4, T**5],
            [0, 1, 2 * T, 3 * T**2, 4 * T**3, 5 * T**4],
            [0, 0, 2, 6 * T, 12 * T**2, 20 * T**3],
        ]
    )
    c = np.linalg.solve(M, np.stack([p0, v0, a0, p1, v1, a1]))
    return (
        sum(c[k] * s**k for k in range(6)),
        sum(k * c[k] * s ** (k - 1) for k in range(1, 6)),
    )


def batch_of(goals) -> TrajectoryBatch:
    """One TrajectoryBatch of (world, stamp, times, P, V, A, mask) goals, joints in controller order."""
    counts = [len(g[2]) for g in goals]
    npoint = sum(counts)

    def table(i):
        return np.concatenate(
            [np.zeros((len(g[2]), 6)) if g[i] is None else g[i] for g in goals] or [np.zeros((0, 6))]
        )

    return TrajectoryBatch(
        worlds=np.array([g[0] for g in goals]),
        start_time=np.array([g[1] for g in goals], dtype=float),
        joint_mask=np.array([g[6] for g in goals], dtype=bool),
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        times=np.concatenate([g[2] for g in goals] or [np.zeros(0)]),
        positions=table(3).reshape(npoint, 6),
        velocities=table(4).reshape(npoint, 6),
        has_velocities=np.array([g[4] is not None for g in goals]),
        accelerations=table(5).reshape(npoint, 6),
        has_accelerations=np.array([g[5] is not None for g in goals]),
    )


@pytest.mark.parametrize("via", ["set_trajectory", "set_trajectories"])
def test_batched_update_matches_a_per_world_reference(via):
    """Mixed splines, future and past stamps, a partial goal, a replaced trajectory: against textbook splines."""
    rng = np.random.default_rng(3)
    spec = batchsim.load("arm")
    nworld, period = 8, 0.01
    sim = FakeSim(spec, nworld, rng)
    yaml_text = arm_yaml(
        "t:\n  type: joint_trajectory_controller/JointTrajectoryController\n",
        "t:\n  ros__parameters:\n    joints: [joint1, joint2, joint3, joint4, joint5, joint6]\n"
        "    command_interfaces: [position]\n    state_interfaces: [position, velocity]\n"
        "    allow_partial_joints_goal: true\n",
    )
    manager = load_controllers(yaml_text, spec, nworld)
    jtc = manager["t"]
    names = spec.state_interfaces
    pcol = [names.index(f"{j}/position") for j in ARM_JOINTS]
    vcol = [names.index(f"{j}/velocity") for j in ARM_JOINTS]
    ccol = [spec.command_interfaces.index(f"{j}/position") for j in ARM_JOINTS]

    # (world, send time, start stamp, times, positions, velocities, accelerations, mode, joint mask)
    goals = []
    every = np.ones(6, bool)
    for w, mode in enumerate(["linear", "cubic", "quintic", "cubic", None, "linear", "quintic", "cubic"]):
        if mode is None:
            continue
        n = int(rng.integers(1, 5))
        times = np.cumsum(rng.uniform(0.05, 0.3, n))
        send = float(rng.choice([0.0, 0.05, 0.13]))
        stamp = 0.0 if w != 3 else send + 0.2  # world 3 starts in the future
        mask = every
        if w == 6:  # a partial goal: the other joints hold
            mask = np.array([True, False, True, False, True, False])
        if w == 7:  # stamped in the past: the points already behind it are dropped
            send, stamp, times = 0.13, 0.02, np.array([0.05, 0.1, 0.3, 0.5])
            n = 4
        P = rng.normal(size=(n, 6))
        V = rng.normal(size=(n, 6)) if mode != "linear" else None
        A = rng.normal(size=(n, 6)) if mode == "quintic" else None
        goals.append((w, send, stamp, times, P, V, A, mode, mask))
    # world 1 gets a new trajectory while its first one runs: it takes over from its start
    goals.append((1, 0.3, 0.0, np.array([0.2, 0.4]), rng.normal(size=(2, 6)), None, None, "linear", every))

    ref_points: dict[int, list] = {}
    ref_mode: dict[int, str] = {}
    hold = sim.state[:, pcol].copy()  # an idle world holds where it was at activation
    t = 0.0
    started: set[int] = set()
    for _ in range(120):
        due = [(i, g) for i, g in enumerate(goals) if abs(t - g[1]) < 1e-9]
        if via == "set_trajectory":
            for _, (w, _send, stamp, times, P, V, A, _mode, mask) in due:
                named = [j for j, m in zip(ARM_JOINTS, mask, strict=True) if m]
                jtc.set_trajectory(
                    w,
                    named,
                    times,
                    P[:, mask],
                    *(x if x is None else x[:, mask] for x in (V, A)),
                    start_time=stamp,
                )
        elif due:
            batch = batch_of(
                [(w, stamp, times, P, V, A, mask) for _, (w, _s, stamp, times, P, V, A, _m, mask) in due]
            )
            assert jtc.set_trajectories(batch) == []
        # the reference's view: the trajectory starts at the first update at or after its stamp
        for i, (w, send, stamp, times, P, V, A, mode, mask) in enumerate(goals):
            if i not in started and t >= max(send, stamp) - 1e-9:
                started.add(i)
                t0 = stamp if stamp > 0 else t
                here = sim.state[w, pcol].copy()
                keep = [k for k in range(len(times)) if t0 + times[k] > t]
                ref_points[w] = [(t, here, sim.state[w, vcol].copy(), np.zeros(6))] + [
                    (
                        t0 + times[k],
                        np.where(mask, P[k], here),
                        np.zeros(6) if V is None else np.where(mask, V[k], 0.0),
                        np.zeros(6) if A is None else np.where(mask, A[k], 0.0),
                    )
                    for k in keep
                ]
                ref_mode[w] = mode
        manager.update(sim, t, period)
        for w in range(nworld):
            if w in ref_points:
                p, v = reference_sample(ref_points[w], ref_mode[w], t)
            else:
                p, v = hold[w], np.zeros(6)
            np.testing.assert_allclose(jtc.reference_position[w], p, atol=1e-9, err_msg=f"world {w} t {t}")
            np.testing.assert_allclose(jtc.reference_velocity[w], v, atol=1e-7, err_msg=f"world {w} t {t}")
            np.testing.assert_allclose(sim.command[w, ccol], p, atol=1e-9)
        np.testing.assert_allclose(jtc.error_position, jtc.reference_position - sim.state[:, pcol])
        sim.advance(period)
        t += period
    assert len(started) == len(goals)


def test_interpolation_none_holds_each_point_until_the_next_ones_time():
    spec = batchsim.load("arm")
    sim = FakeSim(spec, 2, np.random.default_rng(4))
    manager = load_controllers(
        LINEAR_JTC.replace("max_trajectory_points: 6000", "interpolation_method: none"), spec, 2
    )
    jtc = manager["t"]
    manager.update(sim, 0.0, 0.01)
    P, V = np.array([[0.1] * 6, [0.2] * 6]), np.array([[1.0] * 6, [2.0] * 6])
    jtc.set_trajectory(0, ARM_JOINTS, [0.1, 0.2], P, V)  # starts at 0.01: points at 0.11 and 0.21
    seen = {}
    for k in range(1, 30):
        manager.update(sim, 0.01 * k, 0.01)
        seen[k] = (jtc.reference_position[0].copy(), jtc.reference_velocity[0].copy())
        if k == 1:
            here = (jtc.feedback_position[0].copy(), jtc.feedback_velocity[0].copy())
        sim.advance(0.01)
    for k, (p, v) in seen.items():
        want = here if k < 11 else (P[0], V[0]) if k < 21 else (P[1], np.zeros(6))
        np.testing.assert_allclose(p, want[0], atol=1e-12, err_msg=k)
        np.testing.assert_allclose(v, want[1], atol=1e-12, err_msg=k)


def test_batched_diff_drive_matches_a_per_world_reference():
    rng = np.random.default_rng(5)
    spec = batchsim.load("car")
    nworld, period = 5, 0.01
    sim = FakeSim(spec, nworld, rng)
    manager = load_controllers(default_controllers("car"), spec, nworld)
    dd = manager["diff_drive_controller"]
    assert dd.wheel_command_interface is InterfaceKind.EFFORT  # the car's wheels: its wheel PID runs
    names = spec.state_interfaces
    lp, rp = names.index("left_wheel_joint/position"), names.index("right_wheel_joint/position")
    lv, rv = names.index("left_wheel_joint/velocity"), names.index("right_wheel_joint/velocity")
    lc = spec.command_interfaces.index("left_wheel_joint/effort")
    rc = spec.command_interfaces.index("right_wheel_joint/effort")
    sep, r = 0.30, 0.06
    ref = [
        dict(x=0.0, y=0.0, th=0.0, last=None, cmd=(0.0, 0.0), stamp=-1e9, i=[0.0, 0.0]) for _ in range(nworld)
    ]
    t = 0.0
    for _ in range(150):
        for w in range(nworld):
            if rng.random() < 0.2:
                cmd = (float(rng.uniform(-2, 2)), float(rng.uniform(-5, 5)) * (w % 2))
                dd.set_cmd_vel(w, *cmd, stamp=t)
                ref[w]["cmd"], ref[w]["stamp"] = cmd, t
        manager.update(sim, t, period)
        for w in range(nworld):
            s = ref[w]
            lin, ang = s["cmd"] if t - s["stamp"] <= 0.5 else (0.0, 0.0)
            lin, ang = min(max(lin, -1.5), 1.5), min(max(ang, -4.0), 4.0)
            wheels = (sim.state[w, lp], sim.state[w, rp])
            if s["last"] is not None:
                dl, dr = (wheels[0] - s["last"][0]) * r, (wheels[1] - s["last"][1]) * r
                d, a = (dl + dr) / 2, (dr - dl) / sep
                if abs(a) < 1e-6:
                    s["x"] += d * math.cos(s["th"] + a / 2)
                    s["y"] += d * math.sin(s["th"] + a / 2)
                else:
                    rad = d / a
                    s["x"] += rad * (math.sin(s["th"] + a) - math.sin(s["th"]))
                    s["y"] -= rad * (math.cos(s["th"] + a) - math.cos(s["th"]))
                s["th"] += a
            s["last"] = wheels
            want = ((lin - ang * sep / 2) / r, (lin + ang * sep / 2) / r)
            efforts = []
            for k, (target, measured) in enumerate(
                zip(want, (sim.state[w, lv], sim.state[w, rv]), strict=True)
            ):
                e = target - measured
                i = min(max(s["i"][k] + 1.0 * e * period, -2.0), 2.0)
                u = 0.1 * e + i
                clipped = min(max(u, -2.0), 2.0)
                if clipped == u:
                    s["i"][k] = i
                efforts.append(clipped)
            np.testing.assert_allclose(
                dd.odom_pose[w], [s["x"], s["y"], s["th"]], atol=1e-9, err_msg=f"world {w}"
            )
            np.testing.assert_allclose(sim.command[w, [lc, rc]], efforts, atol=1e-9, err_msg=f"world {w}")
        sim.advance(period)
        t += period


def test_forward_command_batched_and_validated():
    spec = batchsim.load("quadruped")
    sim = FakeSim(spec, 4, np.random.default_rng(0))
    manager = load_controllers(default_controllers("quadruped"), spec, 4)
    fcc = manager["effort_controller"]
    manager.update(sim, 0.0, 0.01)
    assert not sim.command.any()  # nothing received yet: interfaces keep their values
    fcc.set_commands(2, np.arange(12.0))
    with pytest.raises(ValueError, match="has 3 values, the controller has 12 joints"):
        fcc.set_commands(1, [1, 2, 3])
    manager.update(sim, 0.01, 0.01)
    cols = [spec.command_interfaces.index(f"{j}/effort") for j in fcc.joints]
    np.testing.assert_array_equal(sim.command[2, cols], np.arange(12.0))
    assert not np.delete(sim.command, 2, axis=0).any()


# ---------------------------------------------------------------- the trajectory controller's PID

QUADRUPED_JOINTS = [
    f"{leg}_{part}" for leg in ("FL", "FR", "HL", "HR") for part in ("hip_abduction", "hip_flexion", "knee")
]


def effort_jtc_yaml(gains: str) -> str:
    """A trajectory controller on the quadruped's effort interfaces, with a `gains:` block."""
    return (
        "controller_manager:\n  ros__parameters:\n    update_rate: 100\n"
        "    t:\n      type: joint_trajectory_controller/JointTrajectoryController\n"
        "t:\n  ros__parameters:\n"
        f"    joints: [{', '.join(QUADRUPED_JOINTS)}]\n"
        "    command_interfaces: [effort]\n    state_interfaces: [position, velocity]\n"
        "    gains:\n" + textwrap.indent(textwrap.dedent(gains), " " * 6)
    )


def test_trajectory_pid_is_ros2_controllers_formula_per_joint_and_world():
    """effort = ff_velocity_scale * v_ref + p e + sum(i e dt) clamped to +-i_clamp + d de, with
    de the velocity error (not a difference quotient); the integral restarts with each trajectory."""
    rng = np.random.default_rng(3)
    nj = len(QUADRUPED_JOINTS)
    p, i, d = rng.uniform(1, 50, nj), rng.uniform(0, 20, nj), rng.uniform(0, 2, nj)
    ff = np.where(np.arange(nj) % 3 == 0, 0.0, rng.uniform(0.5, 1.5, nj))
    clamp = np.where(np.arange(nj) % 2 == 0, np.inf, rng.uniform(0.01, 0.05, nj))
    gains = ""
    for k, j in enumerate(QUADRUPED_JOINTS):  # float() for repr: a YAML number, all its digits
        gains += f"{j}: {{p: {float(p[k])!r}, i: {float(i[k])!r}, d: {float(d[k])!r}"
        gains += f", ff_velocity_scale: {float(ff[k])!r}" if ff[k] else ""
        gains += f", i_clamp: {float(clamp[k])!r}}}\n" if np.isfinite(clamp[k]) else "}\n"
    spec = batchsim.load("quadruped")
    manager = load_controllers(effort_jtc_yaml(gains), spec, 3)
    assert manager.warnings == []
    jtc = manager["t"]
    sim = FakeSim(spec, 3, rng)
    pos = [spec.state_interfaces.index(f"{j}/position") for j in QUADRUPED_JOINTS]
    vel = [spec.state_interfaces.index(f"{j}/velocity") for j in QUADRUPED_JOINTS]
    cols = [spec.command_interfaces.index(f"{j}/effort") for j in QUADRUPED_JOINTS]
    period = 0.01
    integral = np.zeros((3, nj))
    starts = {0: [0, 1], 40: [1], 70: [0]}  # update -> the worlds whose new trajectory starts there
    for step in range(100):
        for w in starts.get(step, []):
            target = rng.normal(scale=0.3, size=nj)
            jtc.set_trajectory(w, QUADRUPED_JOINTS, [0.2, 0.5], [target / 2, target], [target, np.zeros(nj)])
            integral[w] = 0.0
        if step == 55:  # a reset world forgets its integral
            manager.on_reset(sim, [2])
            integral[2] = 0.0
        manager.update(sim, step * period, period)
        e = jtc.reference_position - sim.state[:, pos]
        de = jtc.reference_velocity - sim.state[:, vel]
        integral = np.clip(integral + i * e * period, -clamp, clamp)
        expected = ff * jtc.reference_velocity + p * e + integral + d * de
        np.testing.assert_allclose(
            sim.command[:, cols], expected, rtol=1e-12, atol=1e-12, err_msg=f"step {step}"
        )
        np.testing.assert_allclose(jtc.output, expected, rtol=1e-12, atol=1e-12)
        sim.advance(period)
    assert np.abs(jtc.reference_velocity[[0, 1]]).max() > 0 and (np.abs(integral) == clamp).any()


def test_trajectory_gains_set_at_run_time_drive_that_world_from_its_next_update():
    """gains.<joint>.p set in world 1 (Controller.set_parameters, as upstream's update re-reads
    them): world 1's effort follows the new gain at once, worlds 0 and 2 the YAML's; the integral
    is kept, as control_toolbox's set_gains keeps it."""
    rng = np.random.default_rng(5)
    joint = QUADRUPED_JOINTS[0]
    spec = batchsim.load("quadruped")
    gains = "".join(f"{j}: {{p: 10.0, i: 2.0, d: 0.5}}\n" for j in QUADRUPED_JOINTS)
    manager = load_controllers(effort_jtc_yaml(gains), spec, 3)
    jtc = manager["t"]
    assert jtc.runtime_parameters()[f"gains.{joint}.p"] == 10.0
    sim = FakeSim(spec, 3, rng)
    nj = len(QUADRUPED_JOINTS)
    pos = [spec.state_interfaces.index(f"{j}/position") for j in QUADRUPED_JOINTS]
    vel = [spec.state_interfaces.index(f"{j}/velocity") for j in QUADRUPED_JOINTS]
    cols = [spec.command_interfaces.index(f"{j}/effort") for j in QUADRUPED_JOINTS]
    for w in range(3):
        jtc.set_trajectory(w, QUADRUPED_JOINTS, [0.5], [rng.normal(scale=0.3, size=nj)])
    p, i, d, period = np.full((3, nj), 10.0), np.full((3, nj), 2.0), np.full((3, nj), 0.5), 0.01
    integral = np.zeros((3, nj))
    for step in range(20):
        if step == 10:
            assert jtc.set_parameters(np.array([1]), {f"gains.{joint}.p": 40.0, f"gains.{joint}.i": 0.0}) == ""
            p[1, 0], i[1, 0] = 40.0, 0.0
        manager.update(sim, step * period, period)
        e = jtc.reference_position - sim.state[:, pos]
        de = jtc.reference_velocity - sim.state[:, vel]
        integral = integral + i * e * period
        expected = p * e + integral + d * de
        np.testing.assert_allclose(sim.command[:, cols], expected, rtol=1e-12, atol=1e-12, err_msg=f"step {step}")
        sim.advance(period)


def test_trajectory_gains_are_control_toolbox_pid_parameters_and_a_typo_warns():
    """gains.<joint> takes control_toolbox's PID parameters (clamps, anti-windup) besides
    ff_velocity_scale and i_clamp, as the ros2_control PID path does; any other key is a
    warning naming the controller, the joint and the key, not silence."""
    spec = batchsim.load("quadruped")
    others = "".join(f"{j}: {{p: 10.0}}\n" for j in QUADRUPED_JOINTS[1:])
    manager = load_controllers(
        effort_jtc_yaml(
            f"""\
            {QUADRUPED_JOINTS[0]}:
              p: 1000.0
              i_clamp_min: -1.0
              u_clamp_max: 2.0
              u_clamp_min: -3.0
              antiwindup_strategy: conditional_integration
              antiwindup_stratgy: back_calculation
              ff_velocity_scale: 0.0
              dd: 1.0
            """
        )
        + textwrap.indent(others, " " * 6),
        spec,
        2,
    )
    bad = sorted(w for w in manager.warnings if "gains" in w)
    assert len(bad) == 2, manager.warnings
    for w, key in zip(bad, ("antiwindup_stratgy", "dd"), strict=True):
        assert "controller 't'" in w and f"gains.{QUADRUPED_JOINTS[0]}.{key}: ignored" in w, w
    jtc = manager["t"]
    sim = FakeSim(spec, 2, np.random.default_rng(0))
    col = spec.command_interfaces.index(f"{QUADRUPED_JOINTS[0]}/effort")
    manager.update(sim, 0.0, 0.01)
    target = np.zeros(len(QUADRUPED_JOINTS))
    for w, sign in ((0, 1.0), (1, -1.0)):
        target[0] = sim.state[w, spec.state_interfaces.index(f"{QUADRUPED_JOINTS[0]}/position")] + sign
        jtc.set_trajectory(w, QUADRUPED_JOINTS, [0.0], [target])  # applied at once
    manager.update(sim, 0.01, 0.01)
    np.testing.assert_allclose(sim.command[:, col], [2.0, -3.0])  # p * error (+-1000) clamped to u_clamp

    for gains, message in (
        ("{p: 1.0, antiwindup_strategy: sideways}", ".antiwindup_strategy: unknown strategy 'sideways'"),
        ("{p: fast}", ".p: must be a number, got 'fast'"),
        ("{p: 1.0, u_clamp_min: 2.0, u_clamp_max: 1.0}", ": a clamp's min is above its max"),
    ):
        gains, message = f"{QUADRUPED_JOINTS[0]}: {gains}", f"gains.{QUADRUPED_JOINTS[0]}{message}"
        with pytest.raises(ConfigurationError) as info:
            load_controllers(effort_jtc_yaml(gains + "\n" + others), spec, 1)
        assert "controller 't'" in str(info.value) and message in str(info.value), str(info.value)


# ---------------------------------------------------------------- fleet scale: buffers, the door, batches

LINEAR_JTC = arm_yaml(
    "t:\n  type: joint_trajectory_controller/JointTrajectoryController\n",
    "t:\n  ros__parameters:\n    joints: [joint1, joint2, joint3, joint4, joint5, joint6]\n"
    "    command_interfaces: [position]\n    state_interfaces: [position, velocity]\n"
    "    allow_partial_joints_goal: true\n    max_trajectory_points: 6000\n",
)


class WorldView:
    """One world of a FakeSim, as a one-world sim: its state row, its own command row."""

    def __init__(self, sim: FakeSim, world: int):
        self.sim, self.world = sim, world
        self.nworld = 1
        self.command = np.zeros((1, sim.command.shape[1]))

    @property
    def state(self):
        return self.sim.state[self.world : self.world + 1]


def test_under_churn_every_world_follows_its_own_trajectory_as_if_alone():
    """Trajectories of 1 to 2000 points, replaced, stamped ahead and behind, reset: the fleet's
    shared buffer (reused, grown, compacted, shrunk) gives each world what a one-world controller gives."""
    rng = np.random.default_rng(11)
    spec = batchsim.load("arm")
    nworld, period = 10, 0.01
    sim = FakeSim(spec, nworld, rng)
    fleet = load_controllers(LINEAR_JTC, spec, nworld)
    alone = [load_controllers(LINEAR_JTC, spec, 1) for _ in range(nworld)]
    views = [WorldView(sim, w) for w in range(nworld)]
    jtc = fleet["t"]
    rows_seen = []
    t = 0.0
    for step in range(200):
        goals = []
        for w in np.flatnonzero(rng.random(nworld) < 0.06):
            n = int(rng.choice([1, 3, 12, 400, 2000], p=[0.2, 0.3, 0.3, 0.15, 0.05]))
            times = np.cumsum(rng.uniform(0.0005, 0.02, n))
            mask = rng.random(6) < 0.8 if rng.random() < 0.2 else np.ones(6, bool)
            stamp = float(rng.choice([0.0, t + 0.05, max(t - 0.03, 1e-3)]))
            V = rng.normal(size=(n, 6)) if rng.random() < 0.5 else None
            goals.append((int(w), stamp, times, rng.normal(size=(n, 6)), V, None, mask))
        if goals:
            rejected = {k for k, _ in jtc.set_trajectories(batch_of(goals))}
            for k, (w, *goal) in enumerate(goals):
                alone_rejected = alone[w]["t"].set_trajectories(batch_of([(0, *goal)]))
                assert (k in rejected) == bool(alone_rejected)
        if step in (80, 150):
            worlds = rng.choice(nworld, 3, replace=False)
            fleet.on_reset(sim, worlds)
            for w in worlds:
                alone[w].on_reset(views[w], None)
        fleet.update(sim, t, period)
        for w in range(nworld):
            alone[w].update(views[w], t, period)
        singles = [a["t"] for a in alone]
        np.testing.assert_allclose(
            jtc.reference_position,
            np.concatenate([a.reference_position for a in singles]),
            atol=1e-12,
            err_msg=t,
        )
        np.testing.assert_allclose(
            jtc.reference_velocity,
            np.concatenate([a.reference_velocity for a in singles]),
            atol=1e-9,
            err_msg=t,
        )
        np.testing.assert_array_equal(jtc.executing, np.concatenate([a.executing for a in singles]))
        rows_seen.append(jtc.buffer_rows)
        sim.advance(period)
        t += period
    assert max(rows_seen) >= 2000 and min(rows_seen[100:]) < max(rows_seen)  # it grew and gave rows back


@pytest.mark.parametrize("interpolation", ["splines", "none"])
def test_one_batch_one_by_one_and_alone_give_the_same_reference(interpolation):
    """The same trajectories handed over as one batch, one at a time, and each to a one-world
    controller of its own give the same reference at every update: linear, cubic and quintic
    ones mixed in a batch, partial goals, a world named twice (the later wins), equal lengths
    and mixed ones, replaced while still in their first segment or later, in buffer rows that
    held another kind's points."""
    rng = np.random.default_rng(21)
    spec = batchsim.load("arm")
    nworld, period = 6, 0.01
    yaml_text = LINEAR_JTC
    if interpolation == "none":
        yaml_text = LINEAR_JTC.replace("max_trajectory_points: 6000", "interpolation_method: none")
    sims = [FakeSim(spec, nworld, np.random.default_rng(7)) for _ in range(2)]  # the same states
    batched, single = (load_controllers(yaml_text, spec, nworld) for _ in range(2))
    alone = [load_controllers(yaml_text, spec, 1) for _ in range(nworld)]
    views = [WorldView(sims[0], w) for w in range(nworld)]
    rounds = {0, 1, 8, 9, 10, 25, 40, 41, 55, 70, 71, 90}  # consecutive: replaced in the first segment
    t = 0.0
    for step in range(130):
        if step in rounds:
            every = rng.random() < 0.5
            worlds = np.arange(nworld) if every else np.flatnonzero(rng.random(nworld) < 0.6)
            if len(worlds) > 1 and rng.random() < 0.5:
                worlds = np.append(worlds, worlds[0])  # named twice: the later wins
            same = int(rng.integers(1, 12)) if rng.random() < 0.5 else None  # one length: by block
            goals = []
            for w in worlds:
                n = same or int(rng.integers(1, 12))
                times = np.cumsum(rng.uniform(0.015, 0.04, n))
                mask = rng.random(6) < 0.7 if rng.random() < 0.25 else np.ones(6, bool)
                mask[0] = True
                kind = rng.choice(["linear", "cubic", "quintic"])
                V = None if kind == "linear" else rng.normal(size=(n, 6))
                A = rng.normal(size=(n, 6)) if kind == "quintic" else None
                stamp = float(rng.choice([0.0, t + 0.02, max(t - 0.02, 1e-3)]))
                goals.append((int(w), stamp, times, rng.normal(size=(n, 6)), V, A, mask))
            together = {k for k, _ in batched["t"].set_trajectories(batch_of(goals))}
            for k, goal in enumerate(goals):
                assert (k in together) == bool(single["t"].set_trajectories(batch_of([goal])))
                one = alone[goal[0]]["t"].set_trajectories(batch_of([(0, *goal[1:])]))
                assert (k in together) == bool(one)
        batched.update(sims[0], t, period)
        single.update(sims[1], t, period)
        for w in range(nworld):
            alone[w].update(views[w], t, period)
        a, b, c = batched["t"], single["t"], [one["t"] for one in alone]
        for name, tol in (("reference_position", 1e-12), ("reference_velocity", 1e-9)):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=tol, err_msg=f"{name} {t}")
            each = np.concatenate([getattr(one, name) for one in c])
            np.testing.assert_allclose(getattr(a, name), each, atol=tol, err_msg=f"{name} {t}")
        np.testing.assert_array_equal(a.executing, b.executing)
        np.testing.assert_array_equal(a.executing, np.concatenate([one.executing for one in c]))
        np.testing.assert_allclose(sims[0].command, sims[1].command, atol=1e-12)
        for sim in sims:
            sim.advance(period)
        t += period
    assert all(a.buffer_rows < 1000 for a in (batched["t"], single["t"]))


def test_the_trajectory_buffer_follows_each_worlds_own_trajectory():
    spec = batchsim.load("arm")
    nworld, period = 16, 0.01
    sim = FakeSim(spec, nworld, np.random.default_rng(2))
    manager = load_controllers(LINEAR_JTC, spec, nworld)
    jtc = manager["t"]
    manager.update(sim, 0.0, period)
    short = np.full((2, 6), 0.1)
    for w in range(nworld):
        jtc.set_trajectory(w, ARM_JOINTS, [0.5, 1.0], short)
    small = jtc.buffer_rows
    assert small < 1000
    # one world gets 5000 points (1 ms apart: ten per period) of a ramp
    n = 5000
    times = np.arange(1, n + 1) * 1e-3
    jtc.set_trajectory(3, ARM_JOINTS, times, np.outer(times, np.arange(1, 7)))
    assert jtc.buffer_rows >= n
    t = 0.0
    for _ in range(30):
        t += period
        sim.advance(period)
        manager.update(sim, t, period)
    # linear from the start pose at 0.01 to the ramp's point at 0.011, then on the ramp
    np.testing.assert_allclose(jtc.reference_position[3], (t - 0.01) * np.arange(1, 7), atol=1e-12)
    # a short trajectory takes over: the 5000 rows are given back
    jtc.set_trajectory(3, ARM_JOINTS, [0.5], short[:1])
    manager.update(sim, t + period, period)
    assert jtc.buffer_rows == small
    # the cap: a parameter, with a default, and a reason
    with pytest.raises(ValueError, match=r"6001 points, more than max_trajectory_points \(6000\)"):
        jtc.set_trajectory(0, ARM_JOINTS, np.arange(1, 6002) * 1e-3, np.zeros((6001, 6)))
    default = load_controllers(default_controllers("arm"), spec, 1)["joint_trajectory_controller"]
    assert default.max_trajectory_points == 10_000


def test_a_trajectory_write_would_refuse_is_rejected_at_the_door_with_its_reason():
    sim, manager, loop = running("arm", 3)
    jtc = manager["joint_trajectory_controller"]
    loop.run_period()
    huge = np.zeros((1, 6))
    huge[0, 2] = 1e300
    with pytest.raises(ValueError, match=r"positions must be below 1e\+10 .* got 1e\+300"):
        jtc.set_trajectory(1, ARM_JOINTS, [1.0], huge)
    # every value below 1e10, but the cubic from rest swings to -1.5e10 (bounded by 2e11)
    fast = np.zeros((1, 6))
    fast[0, 0] = 1e9
    with pytest.raises(
        ValueError, match=r"between the start \(from rest\) and point 0 .* may reach 2e\+11 \(a bound\)"
    ):
        jtc.set_trajectory(1, ARM_JOINTS, [100.0], np.zeros((1, 6)), fast)
    good = np.full((1, 6), 0.2)
    batch = batch_of(
        [
            (0, 0.0, np.array([0.5]), good, None, None, np.ones(6, bool)),
            (1, 0.0, np.array([0.5]), huge, None, None, np.ones(6, bool)),
            (2, 0.0, np.array([100.0]), np.zeros((1, 6)), fast, None, np.ones(6, bool)),
        ]
    )
    rejected = jtc.set_trajectories(batch)
    assert [k for k, _ in rejected] == [1, 2] and all(
        r.startswith("joint_trajectory_controller: ") for _, r in rejected
    )
    run_until(loop, 0.6)
    assert not sim.status.any()  # nothing reached write() to be refused
    np.testing.assert_allclose(jtc.reference_position[0], 0.2)
    assert np.abs(jtc.reference_position[[1, 2]]).max() < 1e-9  # the others hold where they were


def test_odometry_from_float32_wheel_angles_far_from_zero_is_exact():
    """A float32 backend's wheel at 1e4 rad has a resolution of ~1e-3 rad, and the device's own
    float32 integration of it (qpos += qvel * dt) then loses 2% of every 0.02 rad step: the
    odometry must follow the wheel's motion, not that angle."""
    spec = batchsim.load("car")
    sim = FakeSim(spec, 2, np.random.default_rng(0))
    manager = load_controllers(default_controllers("car"), spec, 2)
    dd = manager["diff_drive_controller"]
    names = spec.state_interfaces
    pos = [names.index(f"{side}_wheel_joint/position") for side in ("left", "right")]
    vel = [names.index(f"{side}_wheel_joint/velocity") for side in ("left", "right")]
    omega, dt, substeps, radius = 10.0, 0.002, 5, 0.06
    period = dt * substeps
    device = np.array([1e4, 3e4], dtype=np.float32)  # world 0: a float32 device's qpos
    exact = np.array([1e4 + 0.123456789, 3e4 + 0.3])  # world 1: float64 readings, as large

    def read() -> None:
        sim.state[0, pos], sim.state[1, pos] = device, exact
        sim.state[0, vel], sim.state[1, vel] = np.float32(omega), omega

    read()
    manager.update(sim, 0.0, period)
    for k in range(1, 101):
        for _ in range(substeps):
            device += np.float32(omega * dt)
        exact += omega * period
        read()
        manager.update(sim, k * period, period)
        if k >= dd.window:  # the rolling mean holds only whole periods of motion
            np.testing.assert_allclose(dd.odom_twist[:, 0], radius * omega, rtol=1e-9, err_msg=f"period {k}")
    assert abs((device[0] - 1e4) / (omega * 1.0) - 1) > 0.01  # the device's angle did lose its 2%
    np.testing.assert_allclose(dd.odom_pose[:, 0], radius * omega * 1.0, rtol=1e-9)
    np.testing.assert_allclose(dd.odom_pose[:, 1:], 0.0, atol=1e-9)  # float64 differences of 3e4-rad angles


def test_forward_commands_in_a_batch_reject_bad_rows_with_reasons_and_never_raise():
    spec = batchsim.load("quadruped")
    sim = FakeSim(spec, 4, np.random.default_rng(0))
    manager = load_controllers(default_controllers("quadruped"), spec, 4)
    fcc = manager["effort_controller"]
    manager.update(sim, 0.0, 0.002)
    rows = [
        np.full(12, 1.0),
        np.full(12, 2.0),
        [1.0, 2.0],
        np.full(12, np.nan),
        np.full(12, 3e10),
        np.full(12, 4.0),
    ]
    rejected = fcc.set_commands_batch([0, 7, 1, 2, 3, 0], rows)
    assert [k for k, _ in rejected] == [1, 2, 3, 4]
    reasons = dict(rejected)
    assert (
        "world 7 is out of range" in reasons[1] and "has 2 values, the controller has 12 joints" in reasons[2]
    )
    assert "finite" in reasons[3] and "below 1e+10" in reasons[4]
    manager.update(sim, 0.002, 0.002)
    cols = [spec.command_interfaces.index(f"{j}/effort") for j in fcc.joints]
    np.testing.assert_array_equal(
        sim.command[:, cols], np.array([[4.0] * 12] + [[0.0] * 12] * 3)
    )  # last row wins
    # a whole batch of the wrong width: every row rejected, nothing raised
    assert [k for k, _ in fcc.set_commands_batch([1, 2], np.zeros((2, 3)))] == [0, 1]
    assert fcc.set_commands_batch([], np.zeros((0, 12))) == []


def test_cmd_vel_in_a_batch_rejects_bad_rows_with_reasons_and_never_raises():
    spec = batchsim.load("car")
    sim = FakeSim(spec, 4, np.random.default_rng(0))
    manager = load_controllers(default_controllers("car"), spec, 4)
    dd = manager["diff_drive_controller"]
    manager.update(sim, 0.5, 0.01)
    rows = np.array(
        [
            [0.2, 0.1, 0.0],  # world 0, stamp 0: now
            [np.nan, 0.0, 0.0],
            [0.3, 0.0, np.inf],
            [0.4, -0.2, 0.45],  # world 3, stamped 0.45
            [1.0, 0.0, 0.0],  # world 9: out of range
        ]
    )
    rejected = dd.set_cmd_vel_batch([0, 1, 2, 3, 9], rows)
    assert [k for k, _ in rejected] == [1, 2, 4]
    assert "finite" in rejected[0][1] and "stamp" in rejected[1][1] and "out of range" in rejected[2][1]
    # no velocity limit on this axis: a speed write() would refuse is refused here
    unlimited = load_controllers(
        DIFFBOT_STYLE.replace("linear.x.has_velocity_limits: true", "linear.x.has_velocity_limits: false"),
        spec,
        1,
    )
    reason = unlimited["diffbot_base_controller"].set_cmd_vel_batch([0], [[1e300, 0.0]])
    assert "beyond the 1e+10 write() accepts" in reason[0][1]
    manager.update(sim, 0.51, 0.01)
    np.testing.assert_allclose(dd.command_velocity[[0, 3]], [[0.2, 0.1], [0.4, -0.2]])
    assert not dd.command_velocity[[1, 2]].any()
    manager.update(
        sim, 0.96, 0.01
    )  # cmd_vel_timeout 0.5: world 3's stamp (0.45) timed out, world 0's (0.5) not
    assert dd.command_velocity[0, 0] != 0 and dd.command_velocity[3, 0] == 0
    with pytest.raises(ValueError, match="cmd_vel must be finite"):
        dd.set_cmd_vel(0, math.inf, 0.0)


def test_a_trajectory_batch_queues_like_single_trajectories():
    """set_trajectories(batch): each trajectory as set_trajectory would queue it; bad ones come back."""
    from batchsim.controllers import TrajectoryBatch

    sim, manager, loop = running("arm", 4)
    jtc = manager["joint_trajectory_controller"]
    nj = len(jtc.joints)
    goal = np.linspace(0.1, 0.6, nj)
    batch = TrajectoryBatch(
        worlds=np.array([1, 3, 2]),
        start_time=np.zeros(3),
        joint_mask=np.ones((3, nj), bool),
        offsets=np.array([0, 1, 2, 4]),
        times=np.array([0.5, 0.5, 0.5, 0.4]),  # world 2's times go backwards: rejected
        positions=np.tile(goal, (4, 1)),
    )
    rejected = jtc.set_trajectories(batch)
    assert [k for k, _ in rejected] == [2] and "strictly increasing" in rejected[0][1]
    while loop.sim_time < 1.0 - 1e-9:
        loop.run_period()
    np.testing.assert_allclose(jtc.reference_position[[1, 3]], np.tile(goal, (2, 1)), atol=1e-12)
    assert not np.allclose(jtc.reference_position[[0, 2]], goal)


def test_segment_splines_meet_their_ends_for_every_kind_mixed_in_one_batch():
    """splines.coefficients makes a batch with one matrix product and evaluate samples it by
    Horner's rule over coefficient planes (the GPU hosts ran a product per segment 2-4 times
    slower): every kind meets its ends, mixed in one batch, whatever the ends it does not read
    hold, and 4 terms give what 6 give where no segment is quintic."""
    from batchsim.controllers.trajectory import splines

    rng = np.random.default_rng(3)
    n, nj = 40, 3
    kind = rng.choice([splines.HELD, *(int(s) for s in splines.Spline)], n).astype(np.int8)
    ends = rng.normal(size=(6, n, nj))  # p0, p1, v0, v1, a0, a1
    T = rng.uniform(0.05, 0.5, n)
    given = ends.copy()
    for i, k in enumerate(kind):
        ends[~splines._READS[k], i] = np.nan  # not read: anything
    c = splines.coefficients(kind, ends, np.where(kind == splines.HELD, 1.0, T))
    none = np.zeros(n, bool)
    at0 = splines.evaluate(c, np.zeros(n), none)
    atT = splines.evaluate(c, T, none)
    p0, p1, v0, v1, a0, a1 = given
    held, line, cubic, quintic = (kind == k for k in (splines.HELD, splines.LINEAR, splines.CUBIC, splines.QUINTIC))
    np.testing.assert_allclose(at0[0], p0)  # every kind leaves from its first point
    np.testing.assert_allclose(at0[1][held | cubic | quintic], v0[held | cubic | quintic])
    np.testing.assert_allclose(at0[2][held | quintic], a0[held | quintic])
    ends_kinds = line | cubic | quintic
    np.testing.assert_allclose(atT[0][ends_kinds], p1[ends_kinds])  # and reaches the next one
    np.testing.assert_allclose(atT[1][line], ((p1 - p0) / T[:, None])[line])
    np.testing.assert_allclose(atT[1][cubic | quintic], v1[cubic | quintic])
    np.testing.assert_allclose(atT[2][quintic], a1[quintic], rtol=1e-6)
    cubic_only = ~quintic
    s = rng.uniform(0, 0.5, n)
    done = rng.random(n) < 0.3
    four = splines.evaluate(c[:, cubic_only], s[cubic_only], done[cubic_only], terms=splines.CUBIC_TERMS)
    np.testing.assert_allclose(four, splines.evaluate(c[:, cubic_only], s[cubic_only], done[cubic_only]))
    past = splines.evaluate(c, s, done)  # past the last point: the point, at rest
    np.testing.assert_array_equal(past[0][done], c[0][done])
    assert not past[1:, done].any()


def _goals_of_period(k: int, rng: np.random.Generator, nworld: int, period: float):
    """The trajectories a test fleet gets in period k: bursts, partial goals, quintics, stamps."""
    goals = []
    full, half = [True] * 6, [True, True, True, False, False, False]
    if k % 9 == 0:  # every world, in step: their segments are entered together
        times = np.linspace(0.03, 0.15, 5)
        for w in range(nworld):
            goals.append((w, 0.0, times, rng.uniform(-0.3, 0.3, (5, 6)), rng.uniform(-0.5, 0.5, (5, 6)), None, full))
    if k % 11 == 4:
        goals.append((2, 0.0, np.array([0.02, 0.05]), rng.uniform(-0.3, 0.3, (2, 6)), None, None, half))
        goals.append((6, 0.0, np.array([0.03, 0.06, 0.08]), rng.uniform(-0.3, 0.3, (3, 6)), np.zeros((3, 6)), rng.uniform(-1, 1, (3, 6)), full))
    if k % 5 in (0, 1):  # world 7: a point every period, replaced in the next: a segment made ahead for
        # the old trajectory has the index the new one enters (its generation tells them apart)
        times = period * np.arange(1, 5)
        goals.append((7, 0.0, times, rng.uniform(-0.3, 0.3, (4, 6)), rng.uniform(-0.5, 0.5, (4, 6)), None, full))
    if k % 13 == 6:  # stamped a few periods ahead
        goals.append((4, (k + 3) * period, np.array([0.02, 0.04, 0.1]), rng.uniform(-0.3, 0.3, (3, 6)), np.zeros((3, 6)), None, full))
    return goals


HELD_JTC = arm_yaml(
    "t:\n  type: joint_trajectory_controller/JointTrajectoryController\n",
    "t:\n  ros__parameters:\n    joints: [joint1, joint2, joint3, joint4, joint5, joint6]\n"
    "    command_interfaces: [position]\n    state_interfaces: [position, velocity]\n"
    "    allow_partial_joints_goal: true\n    interpolation_method: none\n",
)



def _assert_same_reference(ahead, at_update) -> None:
    """The reference of a fleet whose work was made ahead is the one made at the update, but for
    rounding: polynomials made in batches of other sizes can differ in their last bit, which a
    short segment's accelerations (thousands, cancelling to near 0) carry into differences of
    their size's rounding. A real difference is of the reference's own size."""
    for name in ("reference_position", "reference_velocity", "reference_acceleration"):
        made_at_update = getattr(at_update, name)
        scale = 1e-9 * max(1.0, float(np.abs(made_at_update).max()))
        np.testing.assert_allclose(getattr(ahead, name), made_at_update, rtol=1e-9, atol=scale)
    np.testing.assert_array_equal(ahead.executing, at_update.executing)


def _two_fleets(yaml_text: str, nworld: int):
    """Two identical arm fleets and their controllers `t`: (sims, managers, controllers)."""
    sims = [batchsim.make("arm", nworld, "cpu") for _ in range(2)]
    for sim in sims:
        sim.configure()
        sim.activate()
    managers = [load_controllers(yaml_text, sim.spec, nworld) for sim in sims]
    return sims, managers, [m["t"] for m in managers]


def _count_work(monkeypatch) -> dict[str, int]:
    """Counts, from now on, of the polynomials made ("calls": SegmentPool's calls of
    splines.coefficients) and of the references sampled ("samples": the timeline's evaluate)."""
    from batchsim.controllers.trajectory import pool, timeline

    made = {"calls": 0, "samples": 0}
    coefficients, evaluate = pool.coefficients, timeline.evaluate

    def counted(*args, **kwargs):
        made["calls"] += 1
        return coefficients(*args, **kwargs)

    def sampled(*args, **kwargs):
        made["samples"] += 1
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(pool, "coefficients", counted)
    monkeypatch.setattr(timeline, "evaluate", sampled)
    return made


@pytest.mark.parametrize("yaml_text", [LINEAR_JTC, HELD_JTC], ids=["splines", "none"])
def test_segments_made_while_the_device_steps_give_the_reference_made_at_the_update(yaml_text, monkeypatch):
    """ControllerManager.while_stepping makes ahead the polynomials of the segments the worlds enter
    at the next update (a fleet running in step enters them all in one period: 4096 arms' update
    took 5 ms in such a period on an H100 host). The reference must be the one made at the update,
    through bursts, partial goals, quintics, stamped starts, resets and stops; and the update of a
    period whose segments were made ahead makes none. prepare samples the reference ahead too: an
    update whose worlds keep the polynomials prepare sampled (or take those it made) samples none."""
    nworld = 8
    sims, managers, jtcs = _two_fleets(yaml_text, nworld)  # partial goals allowed
    made = _count_work(monkeypatch)
    period, substeps = 0.01, round(0.01 / sims[0].dt)
    rngs = [np.random.default_rng(5), np.random.default_rng(5)]
    entered_ahead = sampled_ahead = 0
    try:
        for k in range(120):
            t = sum([period] * k, 0.0)  # sim time as SimLoop keeps it (+= period): prepare's t + period is it
            calls, samples = [], []
            for sim, manager, jtc, rng, ahead in zip(sims, managers, jtcs, rngs, (False, True), strict=True):
                sim.read()
                goals = _goals_of_period(k, rng, nworld, period)
                if goals:
                    batch = batch_of(goals)
                    if k % 9 == 0:  # the bursts are goals, some aborted on a tight path tolerance
                        batch.goals = np.arange(1, len(goals) + 1) + 100 * k
                        batch.path_tolerance = np.tile([0.05, -1.0, -1.0], (len(goals), 6, 1))
                    assert not jtc.set_trajectories(batch)
                if k == 50:
                    manager.on_reset(sim, np.array([1, 3]))
                if k == 70:
                    jtc.cancel(np.array([0]), np.array([0]))  # no goal to cancel: nothing happens
                made["calls"] = made["samples"] = 0
                manager.update(sim, t, period)
                calls.append(made["calls"])
                samples.append(made["samples"])
                sim.write()
                if ahead and k % 5 != 1:  # some periods not made ahead: what was made before must not be taken
                    manager.while_stepping(sim, t, period)
                sim.step(substeps)
            _assert_same_reference(jtcs[1], jtcs[0])
            if calls[0] and not calls[1]:
                entered_ahead += 1  # segments entered in this update, every one made ahead
            if samples[0] and not samples[1]:
                sampled_ahead += 1  # the whole reference sampled by prepare
            if k and (k - 1) % 5 != 1 and k != 50 and not calls[1]:  # prepared, nothing made or reset since
                assert not samples[1], f"period {k}: the update sampled what prepare had"
    finally:
        for sim in sims:
            sim.shutdown()
    assert entered_ahead >= 10, entered_ahead
    assert sampled_ahead >= 25, sampled_ahead


OPEN_LOOP_JTC = LINEAR_JTC + "    open_loop_control: true\n"


@pytest.mark.parametrize(
    "yaml_text", [LINEAR_JTC, OPEN_LOOP_JTC, HELD_JTC], ids=["closed loop", "open loop", "none"]
)
def test_first_segments_made_while_the_device_steps_give_the_reference_made_at_the_start(yaml_text, monkeypatch):
    """Trajectories handed over beside the steps start at the next update. Under open_loop_control
    they leave from the reference, known then, and `prepare` makes their first segments ahead (4096
    arms' burst: the start update's largest part). The reference must be the one made at the start,
    through bursts, partial goals (made at the start), stamped starts, trajectories replaced, worlds
    reset and goals canceled after `prepare`; a start whose first segments were all made ahead
    makes none, nor samples the reference prepare sampled. In closed loop (they leave from the
    state measured at the start) none is made ahead."""
    nworld = 8
    sims, managers, jtcs = _two_fleets(yaml_text, nworld)
    made = _count_work(monkeypatch)
    period, substeps = 0.01, round(0.01 / sims[0].dt)
    rngs = [np.random.default_rng(9), np.random.default_rng(9)]
    started_ahead = 0
    try:
        for k in range(120):
            t = sum([period] * k, 0.0)  # sim time as SimLoop keeps it (+= period): prepare's t + period is it
            calls, samples = [], []
            for sim, manager, jtc, rng, ahead in zip(sims, managers, jtcs, rngs, (False, True), strict=True):
                sim.read()
                made["calls"] = made["samples"] = 0
                manager.update(sim, t, period)
                calls.append(made["calls"])
                samples.append(made["samples"])
                sim.write()
                goals = _goals_of_period(k, rng, nworld, period)
                if k % 10 == 7:  # stamped in the past: its first point gone, it leaves from the second row
                    goals.append((2, (k - 3) * period, np.array([0.01, 0.05, 0.09]), rng.uniform(-0.3, 0.3, (3, 6)), None, None, [True] * 6))
                if goals:  # handed over beside the steps, as the bridge does: they start at the next update
                    batch = batch_of(goals)
                    if k % 18 == 0:  # some bursts are goals, aborted on a tight path tolerance
                        batch.goals = np.arange(1, len(goals) + 1) + 100 * k
                        batch.path_tolerance = np.tile([0.05, -1.0, -1.0], (len(goals), 6, 1))
                    assert not jtc.set_trajectories(batch)
                if ahead and k % 7 != 3:  # some periods not made ahead: what was made before must not be taken
                    # nor what was made for another time (every 10th: half a period on)
                    manager.while_stepping(sim, t, period / 2 if k % 10 == 7 else period)
                if k % 9 == 0 and k % 4 == 0:  # after prepare: world 5's trajectory replaced (at once, as
                    # the bridge does when a switch comes in the same read), worlds 1 and 3 reset
                    late = [(5, 0.0, np.array([0.02, 0.07]), rng.uniform(-0.3, 0.3, (2, 6)), np.zeros((2, 6)), None, [True] * 6)]
                    assert not jtc.set_trajectories(batch_of(late))
                    manager.on_reset(sim, np.array([1, 3]))
                if k % 18 == 9:
                    jtc.cancel(np.array([6]), np.array([100 * (k - 9) + 7]))  # world 6's burst goal, before it starts
                sim.step(substeps)
            _assert_same_reference(jtcs[1], jtcs[0])
            if k % 9 == 1 and calls[0] and not calls[1]:
                started_ahead += 1  # a burst started in this update, every first segment made ahead
            if k and (k - 1) % 7 != 3 and (k - 1) % 10 != 7 and (k - 1) % 36 and not calls[1]:
                # prepared for this update, nothing made, replaced or reset since: the reference too
                assert not samples[1], f"period {k}: the update sampled what prepare had"
    finally:
        for sim in sims:
            sim.shutdown()
    if jtcs[0].open_loop:
        assert started_ahead >= 5, started_ahead
    else:
        assert started_ahead == 0, started_ahead


def _run_two_fleets(yaml_text: str, nworld: int, periods: int, goals_at, prepared_for=lambda k, t: t) -> None:
    """`_two_fleets` run in step for `periods` periods of 0.01 s, each handed the goals
    `goals_at(k)` gives (batch_of's tuples) after its update, the second calling
    while_stepping for the time `prepared_for(k, t)` gives: their references must agree every
    period, and every world of the second be on a trajectory at the end."""
    sims, managers, jtcs = _two_fleets(yaml_text, nworld)
    period = 0.01
    try:
        for k in range(periods):
            t = sum([period] * k, 0.0)  # sim time as SimLoop keeps it (+= period): prepare's t + period is it
            for sim, manager, jtc, ahead in zip(sims, managers, jtcs, (False, True), strict=True):
                sim.read()
                manager.update(sim, t, period)
                goals = goals_at(k)
                if goals:
                    assert not jtc.set_trajectories(batch_of(goals))
                if ahead:
                    manager.while_stepping(sim, prepared_for(k, t), period)
                sim.write()
                sim.step(10)
            _assert_same_reference(jtcs[1], jtcs[0])
        assert jtcs[1].executing.all()
    finally:
        for sim in sims:
            sim.shutdown()


def test_a_fleet_that_took_every_polynomial_made_ahead_keeps_them_through_a_prepare_for_another_time():
    """When every world takes the polynomials prepare made, the two blocks trade places rather
    than copy. The block prepare then writes into must not be the one the worlds sample: a
    prepare for a later time (worlds entering a segment then, not at the next update) must leave
    the next update's reference as made at the update."""
    p = np.random.default_rng(4).uniform(-0.3, 0.3, (4, 6))
    times = np.array([0.02, 0.04, 0.06, 0.08])  # a segment every second period, both worlds in step
    _run_two_fleets(
        OPEN_LOOP_JTC,
        2,
        9,
        lambda k: [(w, 0.0, times, p, None, None, [True] * 6) for w in (0, 1)] if k == 0 else [],  # start in period 1
        lambda k, t: t + 0.01 if k in (3, 5) else t,  # periods 3 and 5 follow a take of all: prepared a period on
    )


def test_a_fleet_whose_every_world_enters_a_segment_or_starts_in_one_period_gets_the_reference_made_then():
    """prepare samples ahead from two blocks: the polynomials kept and those it made (segments
    entered, first segments). When every world is in the second, world 1 entering a segment and
    world 0 starting a trajectory, each must get its own reference."""
    p = np.random.default_rng(2).uniform(-0.3, 0.3, (4, 6))
    goals = {
        # world 1: starts at the update of period 1, its second segment at 0.055 s (entered at 0.06)
        0: [(1, 0.0, np.array([0.045, 0.2]), p[:2], None, None, [True] * 6)],
        # world 0: a trajectory that starts at the update of period 6
        5: [(0, 0.0, np.array([0.1, 0.2]), p[2:], None, None, [True] * 6)],
    }
    _run_two_fleets(OPEN_LOOP_JTC, 2, 8, lambda k: goals.get(k, []))
