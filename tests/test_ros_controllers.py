"""The controllers' topics over real DDS: `batchsim` with a controller_manager YAML in a
subprocess, the test talking to it through rclpy. Domains 30-39 belong to this file.

One 8-arm fleet with the arm's default controllers (joint state broadcaster, trajectory
controller on every joint, wrist force/torque broadcaster) serves the checks that follow
in file order.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import need

rclpy = need("rclpy")  # skips where ROS is absent, fails instead under BATCHSIM_FORCE_BACKENDS=1

from builtin_interfaces.msg import Duration  # noqa: E402
from geometry_msgs.msg import TwistStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from ros_fleet import Fleet, domain_id  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from std_srvs.srv import SetBool, Trigger  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from batchsim.controllers import default_controllers  # noqa: E402

pytestmark = pytest.mark.ros

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
JTC = "joint_trajectory_controller"


def sim_time(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def point(positions, seconds: float) -> JointTrajectoryPoint:
    return JointTrajectoryPoint(
        positions=[float(p) for p in positions], time_from_start=Duration(sec=int(seconds), nanosec=int(seconds % 1 * 1e9))
    )


@pytest.fixture(scope="module")
def arms(tmp_path_factory):
    log = tmp_path_factory.mktemp("arms") / "batchsim.log"
    args = ["--worlds", "8", "--model", "arm", "--backend", "cpu", "--controllers", str(default_controllers("arm"))]
    with Fleet(domain_id(30), args, log) as fleet:
        fleet.js = [fleet.latest(JointState, f"/world_{w}/joint_states") for w in range(8)]
        fleet.diag = fleet.diagnostics()
        fleet.wait(lambda: all(s.count > 0 for s in fleet.js), 30, "joint_states")
        yield fleet


def send(fleet, world: int, msg: JointTrajectory) -> None:
    topic = f"/world_{world}/{JTC}/joint_trajectory"
    fleet.advertise(JointTrajectory, topic)
    fleet.wait_subscribed(topic)
    fleet.publish(JointTrajectory, topic, msg)


def test_trajectory_over_ros_to_world_5_of_8(arms):
    ref5 = arms.latest(JointState, f"/world_5/{JTC}/controller_state/reference")  # created on request
    err5 = arms.latest(JointState, f"/world_5/{JTC}/controller_state/error")
    goal = [0.5, -0.4, 0.6, 0.3, -0.5, 0.8]
    msg = JointTrajectory(joint_names=ARM_JOINTS, points=[point([g / 2 for g in goal], 0.5), point(goal, 1.0)])
    send(arms, 5, msg)
    tolerance = 0.04  # rad: the arm's position servos sag under gravity by up to ~0.03
    arms.wait(
        lambda: (
            np.abs(np.array(arms.js[5].msg.position) - goal).max() < tolerance
            and ref5.msg is not None
            and list(ref5.msg.position) == goal
        ),
        timeout=20,
        what="world 5 at the trajectory's last point",
    )
    arms.wait(lambda: err5.msg is not None and np.abs(np.array(err5.msg.position)).max() < tolerance, 10, "error")
    assert np.abs(np.array(arms.js[2].msg.position)).max() < 1e-6  # the other worlds hold still
    assert list(arms.js[5].msg.name) == ARM_JOINTS


def test_a_single_point_at_time_zero_is_applied_over_ros(arms):
    """One point, time_from_start 0, zero stamp: ros2_controllers applies it at once (issue 23:
    it was neither applied nor refused)."""
    goal = [0.3, -0.2, 0.2, 0.1, -0.1, 0.2]
    send(arms, 7, JointTrajectory(joint_names=ARM_JOINTS, points=[point(goal, 0.0)]))
    arms.wait(lambda: np.abs(np.array(arms.js[7].msg.position) - goal).max() < 0.04, 20, "world 7 at the point")


def test_rejected_trajectories_are_logged_and_counted_in_diagnostics(arms):
    bad_name = JointTrajectory(joint_names=["elbow"], points=[point([0.1], 1.0)])
    backwards = JointTrajectory(joint_names=ARM_JOINTS, points=[point([0.1] * 6, 1.0), point([0.2] * 6, 0.5)])
    send(arms, 3, bad_name)  # refused by the worker: it has the names
    send(arms, 4, backwards)  # refused by the controller, in the loop
    topic = f"{JTC}/joint_trajectory"
    arms.wait(
        lambda: int(arms.diag.value("world_3", "bad_commands", "0")) >= 1
        and int(arms.diag.value("world_4", "bad_commands", "0")) >= 1,
        10,
        "both rejections in /diagnostics",
    )
    log = arms.log()
    assert f"rejected command on /world_3/{topic}: unknown joint 'elbow'" in log, log[-2000:]
    assert f"rejected command on /world_4/{topic}: " in log and "strictly increasing" in log, log[-2000:]
    assert "unknown joint 'elbow'" in arms.diag.value("world_3", "last_problem")
    assert "strictly increasing" in arms.diag.value("world_4", "last_problem")
    arms.wait(lambda: arms.diag.value("world_4", f"rejected /world_4/{topic} invalid") == "1", 5, "the count per reason")
    assert arms.diag.value("world_3", f"rejected /world_3/{topic} malformed") == "1"
    assert np.abs(np.array(arms.js[4].msg.position)).max() < 0.02  # the world stayed as it was


def test_a_stray_raw_command_does_not_leave_bad_command_set(arms):
    """The trajectory controller holds every interface; a raw command is refused, counted,
    and the world, whose controller keeps commanding it, is not left marked bad."""
    before = int(arms.diag.value("world_2", "bad_commands", "0"))
    arms.publish_until(
        Float64MultiArray, "/world_2/commands", Float64MultiArray(data=[0.0] * 6),
        lambda: int(arms.diag.value("world_2", "bad_commands", "0")) > before, 10, "the refusal counted",
    )  # fmt: skip
    assert "claimed by controller 'joint_trajectory_controller'" in arms.diag.value("world_2", "last_problem")
    arms.wait(lambda: arms.diag.world("world_2").message == "ok", 5, "world_2 not marked bad")
    time.sleep(1.2)  # two more diagnostics rounds
    assert arms.diag.world("world_2").message == "ok"


def test_a_reset_while_paused_shows_the_broadcasters_state_at_once(arms):
    goal = [0.3] * 6
    send(arms, 6, JointTrajectory(joint_names=ARM_JOINTS, points=[point(goal, 0.3)]))
    arms.wait(lambda: np.abs(np.array(arms.js[6].msg.position) - goal).max() < 0.04, 20, "world_6 at its goal")
    assert arms.call(SetBool, "/batchsim/pause", SetBool.Request(data=True)).success
    time.sleep(0.2)
    count = arms.js[6].count
    assert arms.call(Trigger, "/world_6/reset", Trigger.Request()).success
    arms.wait(lambda: arms.js[6].count > count, 5, "the reset published while paused")
    assert np.abs(np.array(arms.js[6].msg.position)).max() < 0.02  # the joint state broadcaster's copy too
    assert arms.call(SetBool, "/batchsim/pause", SetBool.Request(data=False)).success
    time.sleep(0.5)
    assert np.abs(np.array(arms.js[6].msg.position)).max() < 0.02  # the old goal did not come back


@pytest.mark.parametrize("workers", [None, 2], ids=["default", "2-workers"])
def test_lockstep_waits_for_the_controllers_input(tmp_path, workers):
    """Lockstep with a trajectory controller holding every interface: a period runs once
    every world's trajectory arrived, as it does for raw commands."""
    args = ["--worlds", "2", "--model", "arm", "--backend", "cpu", "--rtf", "0", "--lockstep", "--lockstep-timeout", "30"]
    args += ["--controllers", str(default_controllers("arm"))]
    if workers is not None:
        args += ["--bridge-workers", str(workers)]
    with Fleet(domain_id(32), args, tmp_path / "lockstep.log") as f:
        clock = f.latest(Clock, "/clock")
        f.wait(lambda: clock.msg is not None, 30, "the first period's clock")
        for w in range(2):
            send(f, w, JointTrajectory())
        time.sleep(0.5)
        start = sim_time(clock.msg.clock)
        time.sleep(0.5)
        assert sim_time(clock.msg.clock) - start < 0.02, "lockstep ran without the trajectories"
        for k in range(3):
            before = sim_time(clock.msg.clock)
            for w in range(2):
                send(f, w, JointTrajectory(joint_names=ARM_JOINTS, points=[point([0.05 * (k + 1)] * 6, 1.0)]))
            f.wait(lambda b=before: sim_time(clock.msg.clock) > b, 10, "one period")
            time.sleep(0.3)
            assert sim_time(clock.msg.clock) == pytest.approx(before + 0.01, abs=1e-9)
        before = sim_time(clock.msg.clock)
        send(f, 0, JointTrajectory(joint_names=ARM_JOINTS, points=[point([0.2] * 6, 1.0)]))
        time.sleep(0.5)
        assert sim_time(clock.msg.clock) == before  # world_1's trajectory is missing
        assert f.close() == 0


def test_car_over_ros_cmd_vel_and_odometry(tmp_path):
    """`batchsim --model car` with its default controllers: TwistStamped in, Odometry out."""
    args = ["--worlds", "2", "--model", "car", "--backend", "cpu", "--controllers", str(default_controllers("car"))]
    with Fleet(domain_id(31), args, tmp_path / "cars.log") as fleet:
        odom1 = fleet.latest(Odometry, "/world_1/diff_drive_controller/odom")
        odom0 = fleet.latest(Odometry, "/world_0/diff_drive_controller/odom")
        fleet.wait(lambda: odom1.count > 0 and odom0.count > 0, what="odometry")
        topic = "/world_1/diff_drive_controller/cmd_vel"
        cmd = TwistStamped()  # stamp zero: now, as the stock controller takes it
        cmd.twist.linear.x = 0.5
        fleet.publish(TwistStamped, topic, cmd)
        fleet.wait_subscribed(topic)

        def driving() -> bool:
            fleet.publish(TwistStamped, topic, cmd)
            return odom1.msg.pose.pose.position.x > 0.3

        fleet.wait(driving, timeout=20, what="world 1 driving")
        msg = odom1.msg
        assert (msg.header.frame_id, msg.child_frame_id) == ("world_1/odom", "world_1/base_link")  # tf's names
        assert msg.twist.twist.linear.x == pytest.approx(0.5, abs=0.1)
        assert abs(odom0.msg.pose.pose.position.x) < 1e-3  # world 0 got no cmd_vel
