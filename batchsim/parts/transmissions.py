"""Transmissions at run time: joint values <-> actuator values for every world at once.

The model side (`batchsim.model.transmissions`) builds each `Transmission` as matrices. Here:

- `StateMap` turns the readings of a transmission's joints, gathered at their paired
  actuators' MuJoCo joints, into the joints' own values, in place, after every gather;
- `CommandMap` turns the command interfaces (joint side) into what drives ctrl
  (`RobotSpec.actuator_commands`), and tells which of those a joint's interface stands for.
"""

from __future__ import annotations

import numpy as np

from batchsim.model import CommandMode, InterfaceKind, RobotSpec, StateColumn


class StateMap:
    """In-place actuator -> joint mapping of the readings columns of transmissions' joints."""

    def __init__(self, spec: RobotSpec, columns: list[StateColumn]):
        index = {c.name: k for k, c in enumerate(columns)}
        # (columns, A, b): readings[:, columns] = readings[:, columns] @ A.T + b
        self.groups: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for t in spec.transmissions:
            names = {c.name.rsplit("/", 1)[1] for c in columns if c.name.rsplit("/", 1)[0] in t.joints}
            for iname in sorted(names):
                cols = [index.get(f"{j}/{iname}") for j in t.joints]
                kind = InterfaceKind.of_name(iname)
                if kind is None or None in cols:
                    continue
                a, b = t.joint_from_actuator(kind)
                self.groups.append((np.array(cols, dtype=np.intp), a.T.copy(), b))

    def __bool__(self) -> bool:
        return bool(self.groups)

    def apply(self, readings: np.ndarray) -> None:
        """Map `readings` (k, ncolumn) gathered from the engine, in place."""
        for cols, at, b in self.groups:
            readings[:, cols] = readings[:, cols] @ at + b


class CommandMap:
    """The command interfaces -> `spec.actuator_commands`: inner = command @ matrix + bias.

    Attributes:
      inner: the interfaces that drive ctrl (`spec.actuator_commands`, or `spec.commands`).
      identity: no transmission: inner is the command itself.
    """

    def __init__(self, spec: RobotSpec):
        self.identity = spec.actuator_commands is None
        self.inner = list(spec.commands if self.identity else spec.actuator_commands)
        inner = {c.name: k for k, c in enumerate(self.inner)}
        self.matrix = np.zeros((len(spec.commands), len(self.inner)))
        self.bias = np.zeros(len(self.inner))
        self._stands_for: dict[str, list[int]] = {}
        by_joint = {j: (t, k) for t in spec.transmissions for k, j in enumerate(t.joints)}
        for c, cmd in enumerate(spec.commands):
            if cmd.mode is not CommandMode.TRANSMITTED:
                self.matrix[c, inner[cmd.name]] = 1.0
                self._stands_for[cmd.name] = [inner[cmd.name]]
                continue
            t, k = by_joint[cmd.joint]
            iname = cmd.name.rsplit("/", 1)[1]
            cols = [inner[f"{a}/{iname}"] for a in t.actuators]
            a, b = t.actuator_from_joint(cmd.kind)
            self.matrix[c, cols] = a[:, k]
            self.bias[cols] = b
            self._stands_for[cmd.name] = cols

    def stands_for(self, name: str) -> list[int]:
        """The inner interfaces a command interface drives (KeyError for an unknown name)."""
        return self._stands_for[name]

    def apply(self, command: np.ndarray) -> np.ndarray:
        """(k, ncommand) commands -> (k, ninner) inner commands (the same array without transmissions)."""
        if self.identity:
            return command
        return command @ self.matrix + self.bias
