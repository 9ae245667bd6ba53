"""The ROS stack a robot already has, against a fleet over real DDS: tf, robot_description,
controller_manager services and FollowJointTrajectory, each with rclpy in this process and
`batchsim` in a subprocess. Domains 70-79 belong to this file.

One 4-arm fleet over two bridge workers (worlds 2 and 3 on the last one) serves the checks
in file order.
"""

from __future__ import annotations

import math
import time
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from ros_fleet import Fleet, domain_id, stack_messages

from batchsim.controllers import default_controllers
from batchsim.model import load

pytestmark = pytest.mark.ros

ARM_JOINTS = [f"joint{i}" for i in range(1, 7)]
JTC = "joint_trajectory_controller"


@pytest.fixture(scope="module")
def ros():
    return stack_messages()


@pytest.fixture(scope="module")
def arms(tmp_path_factory, ros):
    log = tmp_path_factory.mktemp("stack") / "batchsim.log"
    args = ["--worlds", "4", "--model", "arm", "--backend", "cpu", "--bridge-workers", "2"]
    args += ["--controllers", str(default_controllers("arm"))]
    with Fleet(domain_id(70), args, log) as fleet:
        fleet.js = [fleet.latest(ros["JointState"], f"/world_{w}/joint_states") for w in range(4)]
        fleet.wait(lambda: all(s.count > 0 for s in fleet.js), 30, "joint_states")
        yield fleet


def _latched(ros):
    return ros["QoSProfile"](depth=100, durability=ros["DurabilityPolicy"].TRANSIENT_LOCAL)


def _goal(ros, positions, seconds=1.0, **extra):
    point = ros["JointTrajectoryPoint"](
        positions=[float(p) for p in positions],
        time_from_start=ros["Duration"](sec=int(seconds), nanosec=int(seconds % 1 * 1e9)),
    )
    goal = ros["FJT"].Goal(trajectory=ros["JointTrajectory"](joint_names=ARM_JOINTS, points=[point]))
    for key, value in extra.items():
        setattr(goal, key, value)
    return goal


def _send(fleet, ros, world: int, goal, feedback=None):
    """(goal handle, result future) of a goal sent to world `world`."""
    client = getattr(fleet, "_fjt", {}).get(world)
    if client is None:
        client = ros["ActionClient"](fleet.node, ros["FJT"], f"/world_{world}/{JTC}/follow_joint_trajectory")
        fleet.__dict__.setdefault("_fjt", {})[world] = client
        assert client.wait_for_server(timeout_sec=40), fleet.log()
        # the server is created when the client appears, and a client that sees the server may
        # not be seen by it yet: an answer it sends before it has matched the client's reader is
        # dropped by rmw_fastrtps ("failed to send response (timeout)"; benchmarks/RESULTS.md,
        # the H100 goal bursts). Discovery settles both ways within a second on one host.
        time.sleep(1.0)
    handle = fleet.send_goal(client, goal, feedback)
    return handle, (handle.get_result_async() if handle.accepted else None)


def _result(fleet, future, timeout=40):
    fleet.wait(future.done, timeout, "the goal's result")
    return future.result()


def test_follow_joint_trajectory_moves_world_2_only_with_feedback(arms, ros):
    others = {w: np.array(arms.js[w].msg.position) for w in (0, 1, 3)}
    feedback = []
    target = [0.4, -0.3, 0.5, 0.2, -0.4, 0.6]
    handle, result = _send(arms, ros, 2, _goal(ros, target, 1.0), feedback.append)
    assert handle.accepted
    answer = _result(arms, result)
    assert answer.status == 4, answer  # SUCCEEDED
    assert answer.result.error_code == 0
    assert feedback and list(feedback[-1].feedback.joint_names) == ARM_JOINTS
    # no goal tolerance (the YAML sets none): SUCCEEDED once the trajectory's time is over, as
    # upstream; the position servos then settle within the arm's ~0.04 rad sag
    arms.wait(lambda: np.abs(np.array(arms.js[2].msg.position) - target).max() < 0.05, 10, "world 2 at the target")
    for w, before in others.items():
        assert np.abs(np.array(arms.js[w].msg.position) - before).max() < 1e-3, f"world {w} moved"


def test_controller_state_is_a_joint_trajectory_controller_state(arms, ros):
    from control_msgs.msg import JointTrajectoryControllerState

    state = arms.latest(JointTrajectoryControllerState, f"/world_2/{JTC}/controller_state")  # created on request
    arms.wait(lambda: state.msg is not None, 20, "controller_state")
    msg = state.msg
    assert list(msg.joint_names) == ARM_JOINTS and msg.speed_scaling_factor == 1.0
    assert np.abs(np.array(msg.reference.positions) - [0.4, -0.3, 0.5, 0.2, -0.4, 0.6]).max() < 1e-9
    assert np.abs(np.array(msg.feedback.positions) - arms.js[2].msg.position).max() < 0.01
    error = np.array(msg.reference.positions) - np.array(msg.feedback.positions)
    assert np.abs(np.array(msg.error.positions) - error).max() < 1e-9


def test_a_goal_outside_its_goal_tolerance_ends_goal_tolerance_violated(arms, ros):
    from control_msgs.msg import JointTolerance

    tight = [JointTolerance(name=j, position=1e-9) for j in ARM_JOINTS]  # the servos sag: never inside
    goal = _goal(ros, [0.1, 0.2, 0.3, 0.0, 0.1, 0.0], 0.5, goal_tolerance=tight, goal_time_tolerance=ros["Duration"](nanosec=200_000_000))
    handle, result = _send(arms, ros, 3, goal)  # world 3: the last bridge worker
    answer = _result(arms, result)
    assert answer.status == 6  # ABORTED
    assert answer.result.error_code == ros["FJT"].Result.GOAL_TOLERANCE_VIOLATED, answer.result.error_string
    assert "goal tolerance" in answer.result.error_string


def test_a_canceled_goal_ends_canceled_and_the_world_holds(arms, ros):
    handle, result = _send(arms, ros, 1, _goal(ros, [1.0, 0.5, -0.5, 0.5, 0.5, 0.5], 6.0))
    arms.wait(lambda: np.abs(arms.js[1].msg.velocity).max() > 0.01, 10, "world 1 moving")
    cancel = handle.cancel_goal_async()
    arms.wait(cancel.done, 10, "the cancel's answer")
    answer = _result(arms, result)
    assert answer.status == 5  # CANCELED
    arms.wait(lambda: np.abs(arms.js[1].msg.velocity).max() < 0.02, 10, "world 1 holding")
    held = np.array(arms.js[1].msg.position)
    assert np.abs(held - [1.0, 0.5, -0.5, 0.5, 0.5, 0.5]).max() > 0.2, "it went on to the goal"


def test_bad_goals_get_upstreams_codes_and_a_reason(arms, ros):
    bad = _goal(ros, [0.0] * 6)
    bad.trajectory.joint_names = ["joint1", "elbow", "joint3", "joint4", "joint5", "joint6"]
    handle, result = _send(arms, ros, 0, bad)
    answer = _result(arms, result)
    assert answer.result.error_code == ros["FJT"].Result.INVALID_JOINTS
    assert "elbow" in answer.result.error_string
    nan = _goal(ros, [math.nan] + [0.0] * 5)
    handle, result = _send(arms, ros, 0, nan)
    answer = _result(arms, result)
    assert answer.result.error_code == ros["FJT"].Result.INVALID_GOAL and answer.result.error_string


def test_long_goals_up_to_max_trajectory_points_are_taken_and_beyond_refused_with_the_reason(arms, ros):
    """A 5,000-point goal outgrew the worker's request ring and was refused as 'too far
    behind'; up to max_trajectory_points (10,000) a trajectory is taken, beyond it refused."""
    n = 5000
    times = np.linspace(0.1, 1.0, n)
    points = [
        ros["JointTrajectoryPoint"](
            positions=[0.2 * t] * 6, time_from_start=ros["Duration"](sec=0, nanosec=int(t * 1e9))
        )
        for t in times
    ]
    goal = ros["FJT"].Goal(trajectory=ros["JointTrajectory"](joint_names=ARM_JOINTS, points=points))
    handle, result = _send(arms, ros, 3, goal)
    answer = _result(arms, result)
    assert answer.status == 4, answer.result.error_string
    too_many = ros["FJT"].Goal(
        trajectory=ros["JointTrajectory"](joint_names=ARM_JOINTS, points=points + points[:1] * 5001)
    )
    handle, result = _send(arms, ros, 3, too_many)
    answer = _result(arms, result)
    assert answer.result.error_code == ros["FJT"].Result.INVALID_GOAL
    assert "10001 points, more than 10000" in answer.result.error_string
    # beyond 100,000 points a goal is rejected at once (accepted, rclpy would keep its hundreds
    # of MB of objects with its result), the reason in the fleet's log
    huge = ros["FJT"].Goal(trajectory=ros["JointTrajectory"](joint_names=ARM_JOINTS, points=points[:1] * 100_001))
    handle, _ = _send(arms, ros, 3, huge)
    assert not handle.accepted
    arms.wait(lambda: "goal rejected: 100001 points, more than 10000" in arms.log(), 10, "the reason in the log")


def test_tf_gives_a_worlds_end_link_pose_equal_to_mujocos(arms, ros):
    """A tf listener written here (TFMessage subscriptions and a lookup up the tree)."""
    transforms: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}

    def take(msg):
        for t in msg.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            transforms[t.child_frame_id] = (t.header.frame_id, np.array([tr.x, tr.y, tr.z]), np.array([q.w, q.x, q.y, q.z]))

    arms.node.create_subscription(ros["TFMessage"], "/tf", take, 100)
    arms.node.create_subscription(ros["TFMessage"], "/tf_static", take, _latched(ros))
    arms.wait(lambda: "world_2/tool" in transforms and "world_2/link6" in transforms, 20, "world 2's tf")
    arms.wait(lambda: np.abs(arms.js[2].msg.velocity).max() < 1e-3, 10, "world 2 at rest")

    def lookup(frame: str) -> tuple[np.ndarray, np.ndarray]:
        pos, quat = np.zeros(3), np.array([1.0, 0, 0, 0])
        while frame in transforms:
            parent, t, q = transforms[frame]
            rotated = np.zeros(3)
            mujoco.mju_rotVecQuat(rotated, pos, q)
            pos = t + rotated
            out = np.zeros(4)
            mujoco.mju_mulQuat(out, q, quat)
            quat, frame = out, parent
        assert frame == "world", frame
        return pos, quat

    pos, quat = lookup("world_2/tool")
    spec = load("arm")
    m = spec.mjmodel
    d = mujoco.MjData(m)
    for name, q in zip(arms.js[2].msg.name, arms.js[2].msg.position, strict=True):
        d.qpos[m.joint(name).qposadr[0]] = q
    mujoco.mj_kinematics(m, d)
    body = m.body("tool").id
    assert np.abs(pos - d.xpos[body]).max() < 2e-3
    assert min(np.abs(quat - d.xquat[body]).max(), np.abs(quat + d.xquat[body]).max()) < 2e-3


def test_robot_description_received_late_is_a_urdf_of_the_arm(arms, ros):
    got = arms.latest(ros["String"], "/world_3/robot_description", qos=_latched(ros))
    arms.wait(lambda: got.msg is not None, 20, "robot_description")
    root = ET.fromstring(got.msg.data)
    assert root.tag == "robot"
    joints = {j.get("name") for j in root.iter("joint")}
    assert set(ARM_JOINTS) <= joints


def test_list_controllers_and_hardware_interfaces(arms, ros):
    srv = ros["srv"]
    answer = arms.call(srv.ListControllers, "/world_2/controller_manager/list_controllers", srv.ListControllers.Request())
    states = {c.name: c for c in answer.controller}
    assert set(states) == {"joint_state_broadcaster", JTC, "wrist_ft_broadcaster"}
    assert states[JTC].state == "active"
    assert states[JTC].type == "joint_trajectory_controller/JointTrajectoryController"
    assert sorted(states[JTC].claimed_interfaces) == sorted(f"{j}/position" for j in ARM_JOINTS)
    hw = arms.call(
        srv.ListHardwareInterfaces, "/world_2/controller_manager/list_hardware_interfaces", srv.ListHardwareInterfaces.Request()
    )
    assert {i.name for i in hw.command_interfaces if i.is_claimed} == {f"{j}/position" for j in ARM_JOINTS}
    assert "joint1/velocity" in {i.name for i in hw.state_interfaces}


def test_switch_controller_deactivates_one_world_only_and_back(arms, ros):
    srv = ros["srv"]
    base = "/world_3/controller_manager"

    def listed(world: int) -> str:
        answer = arms.call(srv.ListControllers, f"/world_{world}/controller_manager/list_controllers", srv.ListControllers.Request())
        return {c.name: c.state for c in answer.controller}[JTC]

    off = arms.call(srv.SwitchController, f"{base}/switch_controller", srv.SwitchController.Request(deactivate_controllers=[JTC], strictness=2))
    assert off.ok, off.message
    assert listed(3) == "inactive" and listed(2) == "active"
    handle, _ = _send(arms, ros, 3, _goal(ros, [0.2] * 6))
    assert not handle.accepted  # an inactive controller takes no goal, as upstream
    unknown = arms.call(
        srv.SwitchController, f"{base}/switch_controller", srv.SwitchController.Request(activate_controllers=["nope"], strictness=2)
    )
    assert not unknown.ok and "nope" in unknown.message
    on = arms.call(srv.SwitchController, f"{base}/switch_controller", srv.SwitchController.Request(activate_controllers=[JTC], strictness=2))
    assert on.ok, on.message
    assert listed(3) == "active"
    handle, result = _send(arms, ros, 3, _goal(ros, [0.2, 0.1, 0.2, 0.1, 0.2, 0.1], 0.5))
    assert handle.accepted and _result(arms, result).status == 4
    # a goal in flight when its controller is deactivated ends as upstream ends it (before:
    # "the world was reset"), and the next activation takes goals again
    handle, result = _send(arms, ros, 3, _goal(ros, [-0.2] * 6, 5.0))
    assert handle.accepted
    off = arms.call(srv.SwitchController, f"{base}/switch_controller", srv.SwitchController.Request(deactivate_controllers=[JTC], strictness=2))
    assert off.ok, off.message
    answer = _result(arms, result)
    assert answer.status == 6, answer  # ABORTED
    assert answer.result.error_code == ros["FJT"].Result.INVALID_GOAL
    assert answer.result.error_string == "Current goal cancelled during deactivate transition."
    on = arms.call(srv.SwitchController, f"{base}/switch_controller", srv.SwitchController.Request(activate_controllers=[JTC], strictness=2))
    assert on.ok, on.message


def test_a_burst_of_controller_manager_calls_is_answered_every_one(arms, ros):
    """5,000 list_controllers calls at once lost all but 11 (issue 47's review found 40-120 lost;
    upstream's answer every call): the services hold up to 10,000 requests now. The client's own
    queue is deep too: one of ROS's default depth (10) loses its answers itself."""
    from rclpy.qos import QoSProfile

    srv = ros["srv"]
    client = arms.node.create_client(srv.ListControllers, "/world_1/controller_manager/list_controllers",
                                     qos_profile=QoSProfile(depth=10_000))  # fmt: skip
    try:
        assert client.wait_for_service(timeout_sec=20)
        answered = []
        with arms.spinning:
            futures = [client.call_async(srv.ListControllers.Request()) for _ in range(2000)]
            for f in futures:
                f.add_done_callback(answered.append)
        arms.wait(lambda: len(answered) == len(futures), 30, f"every answer ({len(answered)} of {len(futures)} so far)")
        assert all(JTC in {c.name for c in f.result().controller} for f in futures)
    finally:
        arms.node.destroy_client(client)


def test_gripper_command_closes_one_worlds_gripper_and_a_blocked_one_stalls(tmp_path, ros):
    from control_msgs.action import GripperCommand
    from test_robots import _demo

    pkg = _demo(tmp_path)
    args = ["--worlds", "2", "--model", str(pkg / "robot.xml"), "--ros2-control", f"{pkg / 'robot.urdf'} use_pid:=true"]
    args += ["--controllers", str(pkg / "controllers.yaml")]
    with Fleet(domain_id(74), args, tmp_path / "gripper.log") as fleet:
        js = [fleet.latest(ros["JointState"], f"/world_{w}/joint_states") for w in range(2)]
        fleet.wait(lambda: all(s.count > 0 for s in js), 30, "joint_states")
        left = list(js[1].msg.name).index("gripper_left_finger_joint")
        client = ros["ActionClient"](fleet.node, GripperCommand, "/world_1/gripper_controller/gripper_cmd")
        assert client.wait_for_server(timeout_sec=40), fleet.log()

        def command(position: float, max_effort: float = 5.0):
            goal = GripperCommand.Goal()
            goal.command.position, goal.command.max_effort = position, max_effort
            future = fleet.send_goal(client, goal).get_result_async()
            fleet.wait(future.done, 40, "the goal's result")
            return future.result()

        closed = command(-0.02)
        assert closed.status == 4 and closed.result.reached_goal and not closed.result.stalled
        assert closed.result.position == pytest.approx(-0.02, abs=0.01)
        # joint_states is another topic: its message of the period the goal was reached may come
        # after the result (CI, under load, once read -0.005 right after it)
        fleet.wait(lambda: abs(js[1].msg.position[left] + 0.02) < 0.01, 10, "world 1's joint_states at the goal")
        assert js[0].msg.position[left] == pytest.approx(0.0, abs=0.005)  # world 0 untouched
        blocked = command(-0.05)  # beyond the finger's range: it stops at -0.03 and stalls
        assert blocked.status == 6 and blocked.result.stalled and not blocked.result.reached_goal
        assert fleet.close() == 0, fleet.log()
