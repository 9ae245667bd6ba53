"""Controllers' topics as data, and the ROS messages built from and parsed into them (no DDS)."""

from __future__ import annotations

import numpy as np
import pytest

import batchsim
from batchsim.controllers import MessageKind, default_controllers, load_controllers
from batchsim.controllers.topics import trajectory_batch


def test_every_default_controller_declares_its_topics():
    """What docs/controllers.md lists per controller type, as data: topic, kind, and the arrays behind them."""
    seen = {}
    for model in ("arm", "car", "quadruped"):
        manager = load_controllers(default_controllers(model), batchsim.load(model), 2)
        for c in manager:
            t = c.topics()
            seen[type(c).__name__] = (
                [(o.topic, o.kind) for o in t.outputs],
                [(i.topic, i.kind) for i in t.inputs],
                t.replaces_joint_states,
            )
            for o in t.outputs:  # every declared field is a (nworld, width) array
                for field, values in o.read().items():
                    assert np.shape(values)[0] == 2, (c.name, o.topic, field)
    jtc = "joint_trajectory_controller"
    assert seen["JointTrajectoryController"] == (
        [(f"{jtc}/controller_state", MessageKind.JOINT_TRAJECTORY_CONTROLLER_STATE)]
        + [(f"{jtc}/controller_state/{p}", MessageKind.JOINT_STATE) for p in ("reference", "feedback", "error")],
        [(f"{jtc}/joint_trajectory", MessageKind.JOINT_TRAJECTORY)],
        False,
    )
    assert seen["JointStateBroadcaster"] == ([("joint_states", MessageKind.JOINT_STATE)], [], True)
    assert seen["DiffDriveController"][1] == [("diff_drive_controller/cmd_vel", MessageKind.TWIST_STAMPED)]
    assert seen["JointGroupEffortController"][1] == [("effort_controller/commands", MessageKind.FLOAT64_MULTI_ARRAY)]


def test_trajectory_batch_maps_joint_names_and_rejects_unknown_or_repeated_ones():
    joints = ("a", "b", "c")
    t = np.array([0.5, 1.0])
    messages = [
        (4, ["c", "a"], t, np.array([[3.0, 1.0], [3.5, 1.5]]), None, None, 0.0),
        (1, ["a", "x"], t, np.zeros((2, 2)), None, None, 0.0),  # unknown joint
        (2, ["b", "b"], t, np.zeros((2, 2)), None, None, 0.0),  # repeated joint
        (0, ["a", "b", "c"], t[:1], np.array([[1.0, 2.0, 3.0]]), np.ones((1, 3)), None, 7.0),
    ]
    batch, index, rejected = trajectory_batch(joints, messages)
    assert index == [0, 3]
    assert [k for k, _ in rejected] == [1, 2] and "unknown joint 'x'" in rejected[0][1]
    assert batch.worlds.tolist() == [4, 0] and batch.offsets.tolist() == [0, 2, 3]
    assert batch.joint_mask.tolist() == [[True, False, True], [True, True, True]]
    np.testing.assert_array_equal(batch.positions[0, [0, 2]], [1.0, 3.0])  # controller order
    assert batch.has_velocities.tolist() == [False, True] and batch.start_time.tolist() == [0.0, 7.0]


@pytest.mark.ros
def test_messages_round_trip_through_rows():
    """fill_message writes rows where ROS wants them; parse_row reads what a sender wrote."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import TwistStamped
    from std_msgs.msg import Float64MultiArray
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from batchsim.controllers import Input, Output
    from ros_bridge.worker.messages import fill_message, new_message, parse_row, parse_trajectory

    out = Output("odom", MessageKind.ODOMETRY, dict, frame_id="{ns}/odom", child_frame_id="{ns}/base")
    built = new_message(out, "world_3")
    rows = {"position": [1, 2, 3], "orientation": [0, 0, 0.6, 0.8], "linear": [4, 5, 6], "angular": [7, 8, 9]}
    msg = fill_message(out.kind, built, rows, Time(sec=2))
    assert msg.header.frame_id == "world_3/odom" and msg.child_frame_id == "world_3/base"
    assert msg.header.stamp == Time(sec=2)
    assert (msg.pose.pose.position.z, msg.pose.pose.orientation.w, msg.twist.twist.angular.x) == (3, 0.8, 7)

    cmd = TwistStamped()
    cmd.twist.linear.x, cmd.twist.angular.z, cmd.header.stamp.sec = 0.5, -0.25, 3
    row = parse_row(Input("cmd_vel", MessageKind.TWIST_STAMPED, list), cmd)
    np.testing.assert_array_equal(row, [0.5, 0, 0, 0, 0, -0.25, 3.0])
    with pytest.raises(ValueError, match="2 values, expected 3"):
        parse_row(Input("commands", MessageKind.FLOAT64_MULTI_ARRAY, list, width=3), Float64MultiArray(data=[1.0, 2.0]))

    traj = JointTrajectory(joint_names=["a", "b"], points=[JointTrajectoryPoint(positions=[1.0])])
    with pytest.raises(ValueError, match="positions must have 2 values"):
        parse_trajectory(traj)
