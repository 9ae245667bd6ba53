"""The ROS face of a controller, as data: which per-world messages it publishes and takes.

ros2_control's controllers create their own publishers and subscriptions; batchsim's run
in the physics loop, vectorized over worlds, while ROS may run in other processes. So a
controller does not touch ROS: `controller.topics()` declares its topics, and the ROS
bridge (ros_bridge/) binds them for every world, builds the messages from the declared
arrays and hands what arrives back through the declared `apply` functions, in bulk.

    topics = jtc.topics()
    topics.inputs[0]    Input("joint_trajectory_controller/joint_trajectory", JOINT_TRAJECTORY, ...)
    topics.outputs[0]   Output("joint_trajectory_controller/controller_state/reference", JOINT_STATE, ...)

Topic names are relative to each world's namespace (`<ns>/<topic>`). No rclpy here.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from batchsim.controllers.joint_names import JointOrder


class MessageKind(enum.Enum):
    """The ROS message types the bridge builds from arrays, or parses into rows."""

    JOINT_STATE = "sensor_msgs/msg/JointState"
    IMU = "sensor_msgs/msg/Imu"
    WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
    ODOMETRY = "nav_msgs/msg/Odometry"
    POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
    FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
    TWIST = "geometry_msgs/msg/Twist"
    TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
    JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
    JOINT_TRAJECTORY_CONTROLLER_STATE = "control_msgs/msg/JointTrajectoryControllerState"


class GoalOutcome(enum.IntEnum):
    """A world's action goal, as a controller's `outcome` array holds it (int8): what the
    bridge turns into the goal's final state and result."""

    NONE = 0  # no goal: none yet, or a topic trajectory replaced it
    ACTIVE = 1  # queued or running
    SUCCEEDED = 2
    PATH_TOLERANCE_VIOLATED = 3
    GOAL_TOLERANCE_VIOLATED = 4
    CANCELED = 5
    ABORTED = 6  # the world was reset
    DEACTIVATED = 7  # aborted: the controller was deactivated in that world (switch_controller)


class ActionKind(enum.Enum):
    """The ROS actions a controller serves, by their type."""

    FOLLOW_JOINT_TRAJECTORY = "control_msgs/action/FollowJointTrajectory"
    GRIPPER_COMMAND = "control_msgs/action/GripperCommand"


#: The fields an Output of each kind is filled from, and each one's width (None: one value
#: per name in `Output.names`). Quaternions are in ROS order (x, y, z, w).
OUTPUT_FIELDS: dict[MessageKind, dict[str, int | None]] = {
    MessageKind.JOINT_STATE: {"position": None, "velocity": None, "effort": None},
    MessageKind.IMU: {"orientation": 4, "angular_velocity": 3, "linear_acceleration": 3},
    MessageKind.WRENCH_STAMPED: {"force": 3, "torque": 3},
    MessageKind.ODOMETRY: {"position": 3, "orientation": 4, "linear": 3, "angular": 3},
    MessageKind.POSE_STAMPED: {"position": 3, "orientation": 4},
    MessageKind.JOINT_TRAJECTORY_CONTROLLER_STATE: {
        f"{part}_{quantity}": None
        for part, quantities in (
            ("reference", ("positions", "velocities", "accelerations")),
            ("feedback", ("positions", "velocities")),
            ("error", ("positions", "velocities")),
            ("output", ("positions",)),
        )
        for quantity in quantities
    },
}

#: What one message of each fixed-size input kind becomes: a row of this many float64.
#: Twist: linear x, y, z, angular x, y, z; TwistStamped adds the header stamp in seconds
#: (0 when the sender left it unset). Float64MultiArray: Input.width values.
INPUT_WIDTH: dict[MessageKind, int] = {MessageKind.TWIST: 6, MessageKind.TWIST_STAMPED: 7}

#: (index of the rejected row or trajectory in the call, the reason)
Rejections = list[tuple[int, str]]


@dataclasses.dataclass
class TrajectoryBatch:
    """Trajectories for several worlds at once, flat (CSR) like a sparse matrix: what a bridge
    hands the controller in one call, however many messages arrived in the period.

    Trajectory k is for world `worlds[k]`; its points are rows `offsets[k]:offsets[k+1]` of
    the flat point arrays. Every per-joint array is in the controller's joint order
    (`JointTrajectoryController.joints`): the sender maps the message's joint_names onto it
    (joint_names.JointOrder) and rejects unknown or repeated names itself, since it has the names.

    Attributes:
      worlds: (n,) int64, the world of each trajectory; a later trajectory for a world
        replaces an earlier one of the same batch.
      start_time: (n,) float64, the header stamp in sim time; 0 starts at the next update.
      joint_mask: (n, njoint) bool, the joints each trajectory names.
      offsets: (n + 1,) int64, offsets[0] == 0, non-decreasing.
      times: (npoint,) float64, each point's time_from_start.
      positions: (npoint, njoint) float64; entries of joints a trajectory does not name are ignored.
      velocities: (npoint, njoint) float64, or None when no trajectory of the batch gives any.
      has_velocities: (n,) bool, which trajectories give velocities (rows of the others are
        ignored); None: all of them, when `velocities` is given.
      accelerations: (npoint, njoint) float64, or None likewise.
      has_accelerations: (n,) bool, or None likewise.
      goals: (n,) int64, the action goal each trajectory carries: a tag the sender chooses
        (> 0), 0 for a plain topic trajectory; None: all 0. An accepted trajectory replaces
        its world's goal (JointTrajectoryController.goal then shows its tag, or 0).
      path_tolerance: (n, njoint, 3) float64, each goal's path tolerance per joint (position,
        velocity, acceleration), as control_msgs/JointTolerance: 0 or NaN (a joint the goal
        leaves out) takes the controller's default, -1 no limit, > 0 this limit; None: defaults.
      goal_tolerance: (n, njoint, 3) float64, the goal tolerances likewise.
      goal_time_tolerance: (n,) float64 seconds, 0 the default (`constraints.goal_time`),
        -1 none (wait), > 0 this; None: defaults. Rows of topic trajectories are ignored.
    """

    worlds: np.ndarray
    start_time: np.ndarray
    joint_mask: np.ndarray
    offsets: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray | None = None
    has_velocities: np.ndarray | None = None
    accelerations: np.ndarray | None = None
    has_accelerations: np.ndarray | None = None
    goals: np.ndarray | None = None
    path_tolerance: np.ndarray | None = None
    goal_tolerance: np.ndarray | None = None
    goal_time_tolerance: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.worlds)

    def select(self, keep: np.ndarray) -> TrajectoryBatch:
        """The trajectories where `keep` `(len(self),)` bool is true, as a batch of their own."""
        idx = np.flatnonzero(keep)
        counts = np.diff(self.offsets)[idx]
        rows = (
            np.concatenate([np.arange(self.offsets[k], self.offsets[k + 1]) for k in idx]) if idx.size else np.zeros(0, np.intp)
        )

        def per_point(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[rows]

        def per_trajectory(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[idx]

        return TrajectoryBatch(
            worlds=self.worlds[idx],
            start_time=self.start_time[idx],
            joint_mask=self.joint_mask[idx],
            offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            times=self.times[rows],
            positions=self.positions[rows],
            velocities=per_point(self.velocities),
            has_velocities=per_trajectory(self.has_velocities),
            accelerations=per_point(self.accelerations),
            has_accelerations=per_trajectory(self.has_accelerations),
            goals=per_trajectory(self.goals),
            path_tolerance=per_trajectory(self.path_tolerance),
            goal_tolerance=per_trajectory(self.goal_tolerance),
            goal_time_tolerance=per_trajectory(self.goal_time_tolerance),
        )


def trajectory_batch(
    joints: Sequence[str],
    messages: Sequence[tuple[int, Sequence[str], np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, float]],
    *,
    goals: Sequence[int] | np.ndarray | None = None,
    path_tolerance: np.ndarray | None = None,
    goal_tolerance: np.ndarray | None = None,
    goal_time_tolerance: Sequence[float] | np.ndarray | None = None,
) -> tuple[TrajectoryBatch, list[int], Rejections]:
    """A TrajectoryBatch from JointTrajectory messages, each as
    (world, joint_names, times (npoint,), positions (npoint, nnamed), velocities or None,
    accelerations or None, header stamp in seconds), its arrays in the message's joint order.

    For FollowJointTrajectory goals, `goals` (nmessage,) gives each message's tag (0: none),
    and `path_tolerance`, `goal_tolerance` (nmessage, njoint, 3) and `goal_time_tolerance`
    (nmessage,) its tolerances, in the controller's joint order (see TrajectoryBatch).

    Returns the batch, the index of the message each trajectory came from, and the
    messages rejected here (an unknown or repeated joint name), with their reasons.
    """
    order = JointOrder(joints)
    nj = len(order)
    kept: list[int] = []
    rejected: Rejections = []
    cols: list[np.ndarray] = []
    for k, (_, names, *_rest) in enumerate(messages):
        try:
            cols.append(order.columns(names))
        except ValueError as e:
            rejected.append((k, str(e)))
        else:
            kept.append(k)
    counts = np.array([len(messages[k][2]) for k in kept], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    npoint = int(offsets[-1])
    mask = np.zeros((len(kept), nj), bool)
    times = np.zeros(npoint)
    positions = np.full((npoint, nj), np.nan)
    has_v = np.zeros(len(kept), bool)
    has_a = np.zeros(len(kept), bool)
    velocities = np.full((npoint, nj), np.nan)
    accelerations = np.full((npoint, nj), np.nan)
    for i, (k, c) in enumerate(zip(kept, cols, strict=True)):
        _, _, t, p, v, a, _ = messages[k]
        lo, hi = offsets[i], offsets[i + 1]
        mask[i, c] = True
        times[lo:hi] = t
        positions[lo:hi][:, c] = p
        if v is not None:
            has_v[i] = True
            velocities[lo:hi][:, c] = v
        if a is not None:
            has_a[i] = True
            accelerations[lo:hi][:, c] = a
    batch = TrajectoryBatch(
        worlds=np.array([messages[k][0] for k in kept], dtype=np.int64),
        start_time=np.array([messages[k][6] for k in kept], dtype=np.float64),
        joint_mask=mask,
        offsets=offsets,
        times=times,
        positions=positions,
        velocities=velocities if has_v.any() else None,
        has_velocities=has_v,
        accelerations=accelerations if has_a.any() else None,
        has_accelerations=has_a,
        goals=None if goals is None else np.asarray(goals, dtype=np.int64).reshape(-1)[kept],
        path_tolerance=None if path_tolerance is None else np.asarray(path_tolerance, dtype=np.float64)[kept],
        goal_tolerance=None if goal_tolerance is None else np.asarray(goal_tolerance, dtype=np.float64)[kept],
        goal_time_tolerance=(
            None
            if goal_time_tolerance is None
            else np.asarray(goal_time_tolerance, dtype=np.float64).reshape(-1)[kept]
        ),
    )
    return batch, kept, rejected


@dataclasses.dataclass(frozen=True)
class Output:
    """A message every world publishes on `<ns>/<topic>` at the bridge's publish rate.

    Attributes:
      topic: the topic under the world's namespace ("joint_states", "arm/controller_state/error").
      kind: the message type.
      read: returns the current values, field -> (nworld, width) float64, the fields of
        OUTPUT_FIELDS[kind] (a JointState may leave out position, velocity or effort);
        called once per publish period in the loop thread, after the controllers' update.
      names: JointState.name, in field column order.
      frame_id, child_frame_id: header frame ids; "{ns}" is replaced by the world's namespace.
      covariance: constant covariances: "orientation", "angular_velocity",
        "linear_acceleration" (9 each; a first value of -1 marks a part the sensor does not
        give, REP 145) for an IMU; "pose", "twist" (36 each) for an Odometry.
    """

    topic: str
    kind: MessageKind
    read: Callable[[], Mapping[str, np.ndarray]]
    names: tuple[str, ...] = ()
    frame_id: str = ""
    child_frame_id: str = ""
    covariance: Mapping[str, Sequence[float]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Transform:
    """A transform every world's tf carries, moved by a controller (the diff drive's
    `odom -> base_link`, as its `enable_odom_tf` publishes it).

    Attributes:
      parent, child: frame ids; "{ns}" is replaced by the world's namespace.
      read: returns (nworld, 7) float64, translation xyz and rotation xyzw of child in
        parent; called once per publish period in the loop thread, after the controllers' update.
    """

    parent: str
    child: str
    read: Callable[[], np.ndarray]


@dataclasses.dataclass(frozen=True)
class Input:
    """Messages every world takes on `<ns>/<topic>`, applied in bulk in the loop thread.

    Attributes:
      topic: the topic under the world's namespace.
      kind: the message type.
      apply: for a fixed-size kind, `apply(worlds (n,) int64, rows (n, width) float64)`;
        for JOINT_TRAJECTORY, `apply(batch: TrajectoryBatch)`. Rows are in arrival order
        (a later row for a world overrides an earlier one). Returns the rejected rows or
        trajectories with their reasons; never raises for bad input.
      width: values per message of a FLOAT64_MULTI_ARRAY input (a message of another
        length is rejected before `apply`, naming both lengths).
      joints: JOINT_TRAJECTORY only: the controller's joints, the order of the batch's
        per-joint arrays (a message's joint names are mapped onto it; an unknown or
        repeated name is rejected before `apply`).
      max_points: JOINT_TRAJECTORY only: a trajectory with more points is rejected before
        `apply` (0: no limit).
    """

    topic: str
    kind: MessageKind
    apply: Callable[..., Rejections]
    width: int = 0
    joints: tuple[str, ...] = ()
    max_points: int = 0

    def row_width(self) -> int:
        """Values per message of a fixed-size input."""
        return self.width if self.kind is MessageKind.FLOAT64_MULTI_ARRAY else INPUT_WIDTH[self.kind]


@dataclasses.dataclass(frozen=True)
class ControllerTopics:
    """Every topic of one controller.

    Attributes:
      controller: the controller's name.
      outputs, inputs: its per-world messages.
      replaces_joint_states: it publishes `<ns>/joint_states` itself (a joint state
        broadcaster), so the bridge's own joint_states stop.
      transforms: what it puts on tf (the bridge publishes them with the world's own).
      action: the action it serves per world, or None. FOLLOW_JOINT_TRAJECTORY's goals go
        through its JOINT_TRAJECTORY input with a goal tag and tolerances; both kinds keep
        per-world `goal` and `outcome` arrays (GoalOutcome) and a `cancel(worlds, goals)`.
    """

    controller: str
    outputs: tuple[Output, ...] = ()
    inputs: tuple[Input, ...] = ()
    replaces_joint_states: bool = False
    action: ActionKind | None = None
    transforms: tuple[Transform, ...] = ()


def each_row(apply_one: Callable[[int, np.ndarray], Any]) -> Callable[[np.ndarray, np.ndarray], Rejections]:
    """An `Input.apply` from a one-world setter that raises ValueError for a bad row."""

    def apply(worlds: np.ndarray, rows: np.ndarray) -> Rejections:
        rejected: Rejections = []
        for k, (world, row) in enumerate(zip(worlds.tolist(), rows, strict=True)):
            try:
                apply_one(world, row)
            except ValueError as e:
                rejected.append((k, str(e)))
        return rejected

    return apply
