"""The actions every world serves, as data, and the loop's side of them. No rclpy here.

A JointTrajectoryController serves `<ns>/<controller>/follow_joint_trajectory`
(control_msgs/action/FollowJointTrajectory) in every world. The workers take the goals
(ros_bridge/worker/actions.py) and hand them to the controller as trajectories with a goal
tag and tolerances, through the same ring and the same `set_trajectories` as the topic's
trajectories: a thousand goals are one batch. The controller checks the tolerances over
every world at once (batchsim/controllers/trajectory/goals.py); the workers read each
world's goal tag and outcome, and the feedback, from a snapshot channel at the action
monitor rate, and finish the goals. A cancel is a CANCEL request through the ring.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable

import numpy as np

#: ros2_controllers' JTC `action_monitor_rate` default (Hz): feedback and outcomes this often
ACTION_MONITOR_RATE = 20.0
#: the channel's first columns: goal tag, outcome (GoalOutcome), the joint that violated
STATUS_COLUMNS = 3


@dataclasses.dataclass(frozen=True)
class TrajectoryActionSpec:
    """FollowJointTrajectory on `<ns>/<controller>/follow_joint_trajectory` in every world.

    Attributes:
      controller: the controller's name.
      controller_index: its column in `cm.active` (its ManagerSpec entry).
      input: the plan input its goals go through (the controller's joint_trajectory input).
      joints: the controller's joints (the order of every per-joint column).
      channel: (nworld, 3 + 6 * njoint): goal tag, outcome, violating joint, then desired
        positions and velocities, actual positions and velocities, error positions and
        velocities.
      every: control periods between two feedback messages (ACTION_MONITOR_RATE).
      max_points: more points are an invalid goal (0: no limit).
    """

    controller: str
    controller_index: int
    input: int
    joints: tuple[str, ...]
    channel: int
    every: int
    max_points: int = 0


def trajectory_action(
    controller, controller_index: int, input_index: int, every: int, max_points: int,
    channel: Callable[[str, int, Callable[[np.ndarray], None]], int],
) -> TrajectoryActionSpec:  # fmt: skip
    """The action of a JointTrajectoryController (its goal/outcome arrays and its state)."""
    c = controller
    nj = len(c.joints)

    def fill(out: np.ndarray) -> None:
        out[:, 0] = c.goal
        out[:, 1] = c.outcome
        out[:, 2] = c.outcome_joint
        at = STATUS_COLUMNS
        for part in (
            c.reference_position, c.reference_velocity, c.feedback_position, c.feedback_velocity,
            c.error_position, c.error_velocity,
        ):  # fmt: skip
            out[:, at : at + nj] = part
            at += nj

    return TrajectoryActionSpec(
        controller=c.name,
        controller_index=controller_index,
        input=input_index,
        joints=tuple(c.joints),
        channel=channel(f"{c.name}.action", STATUS_COLUMNS + 6 * nj, fill),
        every=every,
        max_points=max_points,
    )


_CANCEL = struct.Struct("<qqq")  # action index, world, goal tag


def encode_cancel(action: int, world: int, goal: int) -> bytes:
    return _CANCEL.pack(action, world, goal)


def decode_cancel(payload: np.ndarray) -> tuple[int, int, int]:
    return _CANCEL.unpack_from(payload, 0)


@dataclasses.dataclass(frozen=True)
class GripperActionSpec:
    """GripperCommand on `<ns>/<controller>/gripper_cmd` in every world.

    Attributes:
      controller, controller_index: as TrajectoryActionSpec's.
      channel: (nworld, 6): goal tag, outcome, stalled, reached_goal, position, effort.
      every: control periods between two feedback messages.
    """

    controller: str
    controller_index: int
    channel: int
    every: int


def gripper_action(
    controller, controller_index: int, every: int, channel: Callable[[str, int, Callable[[np.ndarray], None]], int]
) -> GripperActionSpec:
    """The action of a GripperActionController (its goal/outcome arrays and its joint)."""
    c = controller

    def fill(out: np.ndarray) -> None:
        out[:, 0] = c.goal
        out[:, 1] = c.outcome
        out[:, 2] = c.stalled
        out[:, 3] = c.reached
        out[:, 4] = c.measured[:, 0]
        out[:, 5] = c.measured[:, 2]

    return GripperActionSpec(c.name, controller_index, channel(f"{c.name}.action", 6, fill), every)


_GRIPPER = struct.Struct("<qqqdd")  # action index, world, goal tag, position, max_effort


def encode_gripper_goal(action: int, world: int, goal: int, position: float, max_effort: float) -> bytes:
    return _GRIPPER.pack(action, world, goal, position, max_effort)


def decode_gripper_goal(payload: np.ndarray) -> tuple[int, int, int, float, float]:
    return _GRIPPER.unpack_from(payload, 0)
