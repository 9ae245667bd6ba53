"""The gripper action controllers, with a topic in place of their action.

control_msgs (GripperCommand) is not among ROS 2's common interfaces on PyPI, so the
`gripper_cmd` action becomes a topic: `<ns>/<controller>/gripper_cmd`, a
std_msgs/Float64MultiArray `[position, max_effort]` (max_effort <= 0: no limit), and the
action's feedback a sensor_msgs/JointState on `<ns>/<controller>/state` (the joint's
measured position, velocity and effort).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, Output, each_row
from batchsim.model import RobotSpec
from batchsim.pid import PidBank, PidGains


class GripperActionController(Controller):
    """position_controllers/GripperActionController (and parallel_gripper_action_controller's).

    Parameters (stock): `joint`, the gripper's joint (a joint of the ros2_control block, or
    an actuator it names: a tendon-driven gripper); `max_effort`, the default effort limit.
    `goal_tolerance`, `stall_*`, `allow_stalling`, `action_monitor_rate` are accepted (the
    topic has no result to report them in).

    A position target goes to the joint's `position` command interface. If the joint also
    has an `effort` command interface, max_effort is written to it (a parallel gripper's
    force limit); otherwise a position servo's own force range is the limit, and max_effort
    changes nothing (MuJoCo's position actuator has no per-command force limit).

    Attributes:
      position: (nworld,) the last accepted target (NaN: none yet; the joint holds its start).
      max_effort: (nworld,) the last accepted effort limit.
      measured: (nworld, 3) the joint's position, velocity, effort as last read.
    """

    TYPE: ClassVar[str] = "position_controllers/GripperActionController"
    ACCEPTED = (
        *Controller.ACCEPTED, "goal_tolerance", "stall_velocity_threshold", "stall_timeout", "allow_stalling",
        "action_monitor_rate", "max_velocity", "command_interfaces", "state_interfaces",
    )

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.joint = params.string("joint")
        self.default_max_effort = params.number("max_effort", 0.0, minimum=0.0)
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

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self.position[worlds] = np.nan
        self.max_effort[worlds] = self.default_max_effort

    def update(self, sim: Any, time: float, period: float) -> None:
        for k, col in enumerate(self._state):
            if col is not None:
                self.measured[:, k] = sim.state[:, col]
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
        for k, col in enumerate(self._state):
            if col is not None:
                self.measured[:, k] = sim.state[:, col]
        has = ~np.isnan(self.position)
        if not has.any():
            return
        rows = np.flatnonzero(has)
        error = (self.position[rows] - self.measured[rows, 0]).reshape(-1, 1)
        effort = self._pid.update(error, np.full(len(rows), period), rows)[:, 0]
        limit = np.where(self.max_effort[rows] > 0, self.max_effort[rows], np.inf)
        sim.command[rows, self._col] = np.clip(effort, -limit, limit)
