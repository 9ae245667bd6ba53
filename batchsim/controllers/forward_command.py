"""forward_command_controller and its position / velocity / effort flavours.

Each world's last accepted `<ns>/<controller>/commands` array (std_msgs/Float64MultiArray,
one value per joint, in the `joints` order) is written to the claimed interfaces every
period. Until a world receives its first command its interfaces keep the value they
have (the hold pose the hardware starts with), as in ros2_control.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, each_row
from batchsim.model import RobotSpec


class ForwardCommandController(Controller):
    """forward_command_controller/ForwardCommandController: `joints`, `interface_name`.

    Attributes:
      joints: the joints, in command order.
      interface_name: position, velocity or effort.
      commands: (nworld, njoint) the last accepted command of each world (NaN: none yet).
    """

    TYPE: ClassVar[str] = "forward_command_controller/ForwardCommandController"
    INTERFACE: ClassVar[str | None] = None  # fixed by the JointGroup*Controller flavours

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.joints = params.string_list("joints", nonempty=True)
        self.check_joints("joints", self.joints)
        if self.INTERFACE is None:
            self.interface_name = params.string("interface_name")
            key = "interface_name"
        else:
            self.interface_name = self.INTERFACE
            key = "joints"
        self._cols = self.claim(key, [f"{j}/{self.interface_name}" for j in self.joints])
        self.commands = np.full((self.nworld, len(self.joints)), np.nan)
        self._has = np.zeros(self.nworld, bool)
        self._any = False

    def set_commands(self, world: int, values: Sequence[float]) -> None:
        """Accept one world's command (a Float64MultiArray's data); ValueError if malformed."""
        w = self._world(world)
        data = np.asarray(values, dtype=np.float64).reshape(-1)
        if data.shape != (len(self.joints),):
            raise ValueError(
                f"{self.name}: commands has {data.size} values, the controller has "
                f"{len(self.joints)} joints ({', '.join(self.joints)})"
            )
        if not np.isfinite(data).all():
            raise ValueError(f"{self.name}: commands must be finite, got {data.tolist()}")
        self.commands[w] = data
        self._has[w] = True
        self._any = True

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self.commands[worlds] = np.nan
        self._has[worlds] = False
        self._any = bool(self._has.any())

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/commands`, one value per joint."""
        commands = Input(
            f"{self.name}/commands",
            MessageKind.FLOAT64_MULTI_ARRAY,
            each_row(self.set_commands),
            width=len(self.joints),
        )
        return ControllerTopics(self.name, inputs=(commands,))

    def update(self, sim: Any, time: float, period: float) -> None:
        if not self._any:
            return
        if self._has.all():
            sim.command[:, self._cols] = self.commands
        else:
            rows = np.flatnonzero(self._has)
            sim.command[np.ix_(rows, self._cols)] = self.commands[rows]


class JointGroupPositionController(ForwardCommandController):
    """position_controllers/JointGroupPositionController: `joints`, position interfaces."""

    TYPE: ClassVar[str] = "position_controllers/JointGroupPositionController"
    INTERFACE: ClassVar[str | None] = "position"


class JointGroupVelocityController(ForwardCommandController):
    """velocity_controllers/JointGroupVelocityController: `joints`, velocity interfaces."""

    TYPE: ClassVar[str] = "velocity_controllers/JointGroupVelocityController"
    INTERFACE: ClassVar[str | None] = "velocity"


class JointGroupEffortController(ForwardCommandController):
    """effort_controllers/JointGroupEffortController: `joints`, effort interfaces."""

    TYPE: ClassVar[str] = "effort_controllers/JointGroupEffortController"
    INTERFACE: ClassVar[str | None] = "effort"
