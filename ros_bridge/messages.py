"""ROS messages of each MessageKind (batchsim/controllers/topics.py): built from rows of
arrays, or parsed into rows and trajectories.

    msg = new_message(output, "world_3")          # once per world: names, frames, covariances
    fill_message(output.kind, msg, rows, stamp)   # every publish: rows = field -> (width,) values
    row = parse_row(input, msg)                   # an incoming Twist, Float64MultiArray, ...
    traj = parse_trajectory(msg)                  # an incoming JointTrajectory

Float64 sequences are filled in place through NumPy views of the message's own storage,
so publishing a message allocates nothing.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, Twist, TwistStamped, WrenchStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from batchsim.controllers.topics import Input, MessageKind, Output

MESSAGE_TYPES: dict[MessageKind, type] = {
    MessageKind.JOINT_STATE: JointState,
    MessageKind.IMU: Imu,
    MessageKind.WRENCH_STAMPED: WrenchStamped,
    MessageKind.ODOMETRY: Odometry,
    MessageKind.POSE_STAMPED: PoseStamped,
    MessageKind.FLOAT64_MULTI_ARRAY: Float64MultiArray,
    MessageKind.TWIST: Twist,
    MessageKind.TWIST_STAMPED: TwistStamped,
    MessageKind.JOINT_TRAJECTORY: JointTrajectory,
}

# a parsed JointTrajectory: joint_names, times (npoint,), positions (npoint, nnamed),
# velocities or None, accelerations or None, header stamp in seconds
Trajectory = tuple[list[str], np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, float]


def seconds(stamp: Any) -> float:
    """builtin_interfaces/Time in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def float64_view(msg: Any, field: str, n: int) -> np.ndarray:
    """A float64[] field of `msg`, sized n, as a NumPy view that writes into the message.

    rclpy copies an array.array on assignment, so the view is taken of the stored copy.
    """
    setattr(msg, field, array.array("d", bytes(8 * n)))
    return np.frombuffer(getattr(msg, field), dtype=np.float64)


class Built:
    """One world's message of an Output, with views of its float64 sequences."""

    __slots__ = ("msg", "views")

    def __init__(self, msg: Any, views: dict[str, np.ndarray]):
        self.msg = msg
        self.views = views


def new_message(output: Output, namespace: str) -> Built:
    """A world's message of `output`, its constant parts (names, frames, covariances) set."""
    msg = MESSAGE_TYPES[output.kind]()
    views: dict[str, np.ndarray] = {}
    frame = output.frame_id.replace("{ns}", namespace)
    if hasattr(msg, "header"):
        msg.header.frame_id = frame
    kind = output.kind
    if kind is MessageKind.JOINT_STATE:
        msg.name = list(output.names)
        # every field the output declares gets a view; read() may give a subset per call
        for field in ("position", "velocity", "effort"):
            views[field] = float64_view(msg, field, len(output.names))
    elif kind is MessageKind.IMU:
        for part in ("orientation", "angular_velocity", "linear_acceleration"):
            if part in output.covariance:
                setattr(msg, f"{part}_covariance", [float(v) for v in output.covariance[part]])
    elif kind is MessageKind.ODOMETRY:
        msg.child_frame_id = output.child_frame_id.replace("{ns}", namespace)
        if "pose" in output.covariance:
            msg.pose.covariance = [float(v) for v in output.covariance["pose"]]
        if "twist" in output.covariance:
            msg.twist.covariance = [float(v) for v in output.covariance["twist"]]
    return Built(msg, views)


def _xyz(target: Any, row: Any) -> None:
    target.x, target.y, target.z = float(row[0]), float(row[1]), float(row[2])


def _xyzw(target: Any, row: Any) -> None:
    target.x, target.y, target.z, target.w = float(row[0]), float(row[1]), float(row[2]), float(row[3])


def fill_message(kind: MessageKind, built: Built, rows: dict[str, np.ndarray], stamp: Any) -> Any:
    """Write one world's rows (field -> (width,)) and the stamp into its message; returns it."""
    msg = built.msg
    if kind is MessageKind.JOINT_STATE:
        msg.header.stamp = stamp
        for field, view in built.views.items():
            row = rows.get(field)
            if row is None:
                view.fill(np.nan)
            else:
                view[:] = row
    elif kind is MessageKind.IMU:
        msg.header.stamp = stamp
        _xyzw(msg.orientation, rows["orientation"])
        _xyz(msg.angular_velocity, rows["angular_velocity"])
        _xyz(msg.linear_acceleration, rows["linear_acceleration"])
    elif kind is MessageKind.WRENCH_STAMPED:
        msg.header.stamp = stamp
        _xyz(msg.wrench.force, rows["force"])
        _xyz(msg.wrench.torque, rows["torque"])
    elif kind is MessageKind.ODOMETRY:
        msg.header.stamp = stamp
        _xyz(msg.pose.pose.position, rows["position"])
        _xyzw(msg.pose.pose.orientation, rows["orientation"])
        _xyz(msg.twist.twist.linear, rows["linear"])
        _xyz(msg.twist.twist.angular, rows["angular"])
    elif kind is MessageKind.POSE_STAMPED:
        msg.header.stamp = stamp
        _xyz(msg.pose.position, rows["position"])
        _xyzw(msg.pose.orientation, rows["orientation"])
    else:
        raise ValueError(f"{kind.value} is not an output message kind")
    return msg


def parse_row(input: Input, msg: Any) -> np.ndarray:
    """A fixed-size input message as its row; ValueError naming what is wrong."""
    kind = input.kind
    if kind is MessageKind.FLOAT64_MULTI_ARRAY:
        row = np.asarray(msg.data, dtype=np.float64)
        if row.shape != (input.width,):
            raise ValueError(f"{row.size} values, expected {input.width}")
        return row
    if kind is MessageKind.TWIST or kind is MessageKind.TWIST_STAMPED:
        twist = msg if kind is MessageKind.TWIST else msg.twist
        values = [
            twist.linear.x,
            twist.linear.y,
            twist.linear.z,
            twist.angular.x,
            twist.angular.y,
            twist.angular.z,
        ]
        if kind is MessageKind.TWIST_STAMPED:
            values.append(seconds(msg.header.stamp))
        return np.array(values, dtype=np.float64)
    raise ValueError(f"{kind.value} is not a fixed-size input kind")


def parse_trajectory(msg: JointTrajectory) -> Trajectory:
    """A JointTrajectory as arrays in its own joint order; ValueError for ragged points."""
    names = list(msg.joint_names)
    n = len(names)
    points = msg.points
    if any(len(p.positions) != n for p in points):
        raise ValueError(f"every point's positions must have {n} values")
    has_v = any(len(p.velocities) for p in points)
    has_a = any(len(p.accelerations) for p in points)
    if has_v and any(len(p.velocities) != n for p in points):
        raise ValueError(f"every point's velocities must have {n} values or none")
    if has_a and any(len(p.accelerations) != n for p in points):
        raise ValueError(f"every point's accelerations must have {n} values or none")
    times = np.array([seconds(p.time_from_start) for p in points], dtype=np.float64)
    positions = np.array([p.positions for p in points], dtype=np.float64).reshape(len(points), n)
    velocities = np.array([p.velocities for p in points], dtype=np.float64) if has_v else None
    accelerations = np.array([p.accelerations for p in points], dtype=np.float64) if has_a else None
    return names, times, positions, velocities, accelerations, seconds(msg.header.stamp)
