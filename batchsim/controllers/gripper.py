"""The gripper action controllers, vectorized over worlds.

The ROS bridge serves their `<ns>/<controller>/gripper_cmd` action
(control_msgs/action/GripperCommand, ros_bridge/worker/actions.py) and hands the goals
here through `set_goals`; each update decides every world's goal as upstream's
gripper_action_controller does: within `goal_tolerance` of the target -> SUCCEEDED
(reached_goal); not moving faster than `stall_velocity_threshold` for `stall_timeout`
s -> stalled: SUCCEEDED with `allow_stalling`, else ABORTED. A cancel holds the
gripper where it is.

Deprecated, kept for one release: the topic that stood in for the action before
control_msgs could be built, `<ns>/<controller>/gripper_cmd` as a
std_msgs/Float64MultiArray `[position, max_effort]` (max_effort <= 0: the default), and
`<ns>/<controller>/state` (sensor_msgs/JointState, the joint's position, velocity, effort).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import (
    ActionKind,
    ControllerTopics,
    GoalOutcome,
    Input,
    MessageKind,
    Output,
    each_row,
)
from batchsim.model import RobotSpec
from batchsim.pid import PidBank, PidGains


class GripperActionController(Controller):
    """position_controllers/GripperActionController (and parallel_gripper_action_controller's).

    Parameters (stock, upstream's defaults): `joint`, the gripper's joint (a joint of the
    ros2_control block, or an actuator it names: a tendon-driven gripper); `max_effort`
    (0), the default effort limit; `goal_tolerance` (0.01), `stall_velocity_threshold`
    (0.001), `stall_timeout` (1.0 s), `allow_stalling` (false).

    A position target goes to the joint's `position` command interface. If the joint also
    has an `effort` command interface, max_effort is written to it (a parallel gripper's
    force limit); otherwise a position servo's own force range is the limit, and max_effort
    changes nothing (MuJoCo's position actuator has no per-command force limit).

    Attributes:
      position: (nworld,) the last accepted target (NaN: none yet; the joint holds its start).
      max_effort: (nworld,) the last accepted effort limit.
      measured: (nworld, 3) the joint's position, velocity, effort as last read.
      goal: (nworld,) int64, the tag of the action goal the world follows or last followed (0: none).
      outcome: (nworld,) int8 GoalOutcome of that goal (ACTIVE, SUCCEEDED, ABORTED, CANCELED).
      stalled, reached: (nworld,) bool, the goal's result flags (as last decided).
    """

    TYPE: ClassVar[str] = "position_controllers/GripperActionController"
    ACCEPTED = (
        *Controller.ACCEPTED, "action_monitor_rate", "max_velocity", "command_interfaces", "state_interfaces",
    )

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.joint = params.string("joint")
        self.default_max_effort = params.number("max_effort", 0.0, minimum=0.0)
        self.goal_tolerance = params.number("goal_tolerance", 0.01, minimum=0.0)
        self.stall_velocity_threshold = params.number("stall_velocity_threshold", 0.001, minimum=0.0)
        self.stall_timeout = params.number("stall_timeout", 1.0, minimum=0.0)
        self.allow_stalling = params.boolean("allow_stalling", False)
        self._col = self._claim_command()
        effort = f"{self.joint}/effort"
        self._effort_col = (
            int(self.claim("joint", [effort])[0]) if self.effort_limit_interface and effort in self._command_names else None
        )
        self._state = [
            int(self.state_columns("joint", [f"{self.joint}/{k}"])[0]) if f"{self.joint}/{k}" in self._state_names else None
            for k in ("position", "velocity", "effort")
        ]
        self.position = np.full(self.nworld, np.nan)
        self.max_effort = np.full(self.nworld, self.default_max_effort)
        self.measured = np.full((self.nworld, 3), np.nan)
        self.goal = np.zeros(self.nworld, np.int64)
        self.outcome = np.zeros(self.nworld, np.int8)
        self.stalled = np.zeros(self.nworld, bool)
        self.reached = np.zeros(self.nworld, bool)
        self._moved_at = np.zeros(self.nworld)  # sim time the joint last moved, per world

    effort_limit_interface: ClassVar[bool] = True

    def _claim_command(self) -> int:
        return int(self.claim("joint", [f"{self.joint}/position"])[0])

    def set_goal(self, world: int, values: Sequence[float]) -> None:
        """Accept one world's goal `[position, max_effort]`; ValueError if malformed."""
        w = self._world(world)
        data = np.asarray(values, dtype=np.float64).reshape(-1)
        if data.shape != (2,) or not np.isfinite(data).all():
            raise ValueError(f"{self.name}: gripper_cmd must be [position, max_effort], finite, got {data.tolist()}")
        self.position[w] = data[0]
        self.max_effort[w] = data[1] if data[1] > 0 else self.default_max_effort
        self._drop_goals(np.array([w]))

    def set_goals(self, worlds: np.ndarray, goals: np.ndarray, positions: np.ndarray, max_efforts: np.ndarray) -> list[tuple[int, str]]:
        """GripperCommand goals: world `worlds[k]` goes to `positions[k]` with effort limit
        `max_efforts[k]` (<= 0: the default) under tag `goals[k]`, replacing its goal.
        Returns the rejected ones (a value not finite) with their reasons."""
        worlds, goals = np.asarray(worlds, np.int64), np.asarray(goals, np.int64)
        positions, max_efforts = np.asarray(positions, np.float64), np.asarray(max_efforts, np.float64)
        bad = ~(np.isfinite(positions) & np.isfinite(max_efforts))
        rejected = [(int(k), f"{self.name}: position and max_effort must be finite") for k in np.flatnonzero(bad)]
        ok = ~bad
        w = worlds[ok]
        self.position[w] = positions[ok]
        self.max_effort[w] = np.where(max_efforts[ok] > 0, max_efforts[ok], self.default_max_effort)
        self.goal[w] = goals[ok]
        self.outcome[w] = GoalOutcome.ACTIVE
        self.stalled[w] = False
        self.reached[w] = False
        self._moved_at[w] = self.time
        return rejected

    def cancel(self, worlds: np.ndarray, goals: np.ndarray) -> None:
        """Worlds whose active goal has the given tag stop where they are (CANCELED)."""
        worlds = np.asarray(worlds, np.int64)
        hit = worlds[(self.goal[worlds] == np.asarray(goals)) & (self.outcome[worlds] == GoalOutcome.ACTIVE)]
        self.outcome[hit] = GoalOutcome.CANCELED
        self.position[hit] = self.measured[hit, 0]

    def _drop_goals(self, worlds: np.ndarray) -> None:
        """A topic command or a reset replaces the worlds' goals."""
        self.goal[worlds] = 0
        self.outcome[worlds] = GoalOutcome.NONE

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self.position[worlds] = np.nan
        self.max_effort[worlds] = self.default_max_effort
        active = worlds[self.outcome[worlds] == GoalOutcome.ACTIVE]
        self.outcome[active] = GoalOutcome.ABORTED

    def deactivate(self, sim: Any, worlds: np.ndarray) -> None:
        active = worlds[self.outcome[worlds] == GoalOutcome.ACTIVE]
        self.reset(sim, worlds)  # a subclass's own reset too
        self.outcome[active] = GoalOutcome.DEACTIVATED

    def _decide(self, time: float) -> None:
        """Every active goal's outcome, as upstream's check_for_success, at once."""
        active = np.flatnonzero(self.outcome == GoalOutcome.ACTIVE)
        if not active.size:
            return
        pos, vel = self.measured[active, 0], self.measured[active, 1]
        reached = np.abs(self.position[active] - pos) < self.goal_tolerance
        moving = np.abs(np.nan_to_num(vel)) > self.stall_velocity_threshold
        self._moved_at[active[moving]] = time
        stalled = ~reached & ~moving & (time - self._moved_at[active] > self.stall_timeout)
        self.reached[active] = reached
        self.stalled[active] = stalled
        self.outcome[active[reached]] = GoalOutcome.SUCCEEDED
        self.outcome[active[stalled]] = GoalOutcome.SUCCEEDED if self.allow_stalling else GoalOutcome.ABORTED

    def _measure(self, sim: Any, time: float) -> None:
        for k, col in enumerate(self._state):
            if col is not None:
                self.measured[:, k] = sim.state[:, col]
        self._decide(time)

    def update(self, sim: Any, time: float, period: float) -> None:
        self._measure(sim, time)
        has = ~np.isnan(self.position)
        if has.any():
            sim.command[has, self._col] = self.position[has]
            if self._effort_col is not None:
                sim.command[has, self._effort_col] = self.max_effort[has]

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/gripper_cmd` in, `<ns>/<controller>/state` out."""
        fields = {"position": self.measured[:, 0:1], "velocity": self.measured[:, 1:2], "effort": self.measured[:, 2:3]}
        return ControllerTopics(
            self.name,
            inputs=(Input(f"{self.name}/gripper_cmd", MessageKind.FLOAT64_MULTI_ARRAY, each_row(self.set_goal), width=2),),
            outputs=(Output(f"{self.name}/state", MessageKind.JOINT_STATE, lambda: fields, names=(self.joint,)),),
            action=ActionKind.GRIPPER_COMMAND,
        )


class ParallelGripperActionController(GripperActionController):
    """parallel_gripper_action_controller/GripperActionController: as the position flavour."""

    TYPE: ClassVar[str] = "parallel_gripper_action_controller/GripperActionController"


class EffortGripperActionController(GripperActionController):
    """effort_controllers/GripperActionController: the joint's `effort` interface, driven by
    a PID on the position error (`gains.<joint>.p`, `.i`, `.d`, as the stock controller
    reads them), clamped to +-max_effort."""

    TYPE: ClassVar[str] = "effort_controllers/GripperActionController"
    ACCEPTED = (*GripperActionController.ACCEPTED, "gains")
    effort_limit_interface: ClassVar[bool] = False

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        if self._state[0] is None:
            raise params.error("joint", f"the model exposes no {self.joint}/position state interface for the PID")
        gains = {k: params.number(f"gains.{self.joint}.{k}", 0.0) for k in ("p", "i", "d")}
        self._pid = PidBank([PidGains(**gains)], self.nworld)
        self._last = np.full(self.nworld, np.nan)

    def _claim_command(self) -> int:
        return int(self.claim("joint", [f"{self.joint}/effort"])[0])

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        super().reset(sim, worlds)
        self._pid.reset(worlds)
        self._last[worlds] = np.nan

    def update(self, sim: Any, time: float, period: float) -> None:
        self._measure(sim, time)
        has = ~np.isnan(self.position)
        if not has.any():
            return
        rows = np.flatnonzero(has)
        error = (self.position[rows] - self.measured[rows, 0]).reshape(-1, 1)
        effort = self._pid.update(error, np.full(len(rows), period), rows)[:, 0]
        limit = np.where(self.max_effort[rows] > 0, self.max_effort[rows], np.inf)
        sim.command[rows, self._col] = np.clip(effort, -limit, limit)
