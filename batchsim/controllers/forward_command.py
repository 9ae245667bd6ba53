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

from batchsim.controllers.base import Controller, Params, last_per_world, rows_all
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind
from batchsim.model import RobotSpec
from batchsim.types import MAX_COMMAND


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
        """Accept one world's command (a Float64MultiArray's data); ValueError if malformed.

        The one-world convenience over `set_commands_batch`.
        """
        self._world(world)
        rejected = self.set_commands_batch([world], [np.asarray(values, dtype=np.float64).reshape(-1)])
        if rejected:
            raise ValueError(rejected[0][1])

    def set_commands_batch(
        self, worlds: Sequence[int] | np.ndarray, rows: Sequence[Sequence[float]] | np.ndarray
    ) -> list[tuple[int, str]]:
        """Accept the commands of several worlds at once; a later row for a world wins.

        Args:
          worlds: (n,) int, the world of each row.
          rows: (n, njoint) float64, or n sequences of any length (each checked on its own).

        Returns:
          (index, reason) for each rejected row: a world out of range, a wrong number of
          values, a NaN or inf, or a value of MAX_COMMAND (1e10) or more, which write()
          would refuse. Those worlds keep their previous command. Never raises for a bad row.

        Raises:
          ValueError: `worlds` and `rows` differ in length (the caller's bug).
        """
        w, rejected = self._batch_worlds(worlds)
        nj = len(self.joints)
        values, lengths = _rows(rows, len(w), nj)
        if len(values) != len(w):
            raise ValueError(f"{self.name}: {len(w)} worlds but {len(values)} rows of commands")
        with np.errstate(invalid="ignore"):
            finite = rows_all(np.isfinite(values))
            small = rows_all(np.abs(values) < MAX_COMMAND)
        for k in np.flatnonzero((lengths != nj) | ~finite | ~small).tolist():
            if k in rejected:
                continue
            if lengths[k] < 0:
                reason = "commands must be a list of numbers"
            elif lengths[k] != nj:
                reason = f"commands has {lengths[k]} values, the controller has {nj} joints ({', '.join(self.joints)})"
            elif not finite[k]:
                reason = f"commands must be finite, got {values[k].tolist()}"
            else:
                reason = (
                    f"commands must be below {MAX_COMMAND:g} in magnitude (write() refuses larger), "
                    f"got {values[k].tolist()}"
                )
            rejected[k] = f"{self.name}: {reason}"
        good = np.ones(len(w), bool)
        good[list(rejected)] = False
        good = np.flatnonzero(good)
        keep = good[last_per_world(w[good])]
        self.commands[w[keep]] = values[keep]
        self._has[w[keep]] = True
        self._any = self._any or bool(keep.size)
        return sorted(rejected.items())

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self.commands[worlds] = np.nan
        self._has[worlds] = False
        self._any = bool(self._has.any())

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/commands`, one value per joint."""
        commands = Input(
            f"{self.name}/commands",
            MessageKind.FLOAT64_MULTI_ARRAY,
            self.set_commands_batch,
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


def _rows(rows: Any, n: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, width) float64 values (NaN in a row of another length) and each row's length (n,), -1: not numbers."""
    try:
        values = np.asarray(rows, dtype=np.float64)
    except ValueError:  # ragged: rows of different lengths
        values = None
    if values is not None and values.ndim == 2:
        if values.shape[1] == width:
            return values, np.full(len(values), width)
        return np.full((len(values), width), np.nan), np.full(len(values), values.shape[1])
    if values is not None and values.ndim == 1 and n == 0:
        return np.zeros((0, width)), np.zeros(0, np.int64)
    out = np.full((len(rows), width), np.nan)
    lengths = np.zeros(len(rows), np.int64)
    for k, row in enumerate(rows):
        try:
            r = np.asarray(row, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            lengths[k] = -1  # not numbers
            continue
        lengths[k] = r.size
        if r.size == width:
            out[k] = r
    return out, lengths
