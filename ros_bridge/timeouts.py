"""The command timeout (BridgeOptions.command_timeout): a world that has had no command for that
long holds its measured position and zero velocity and effort on the interfaces no controller
owns, until its next command; the log names it once. Physics side; no rclpy here."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from batchsim.contract import Contract
from batchsim.model import InterfaceKind


class CommandTimeouts:
    """Per world: the sim time of its last command and whether it timed out.

    Attributes:
      timed_out: (nworld,) bool, the worlds holding safe commands now.
    """

    def __init__(self, sim: Contract, timeout: float | None, free: np.ndarray, namespaces: Sequence[str], warn: Callable[[str, str], None]):
        self.timeout = timeout
        self.free = free  # (ncommand,) bool: the interfaces no controller owns
        self.namespaces = namespaces
        self.warn = warn
        self.last_command = np.full(sim.nworld, np.inf)  # sim time of the last command; inf: never
        self.timed_out = np.zeros(sim.nworld, dtype=bool)
        self._safe = safe_plan(sim)

    def heard(self, worlds: np.ndarray, time: float) -> None:
        """`worlds` (a mask or rows) got a command at sim `time`."""
        self.last_command[worlds] = time
        self.timed_out[worlds] = False

    def forget(self, worlds: np.ndarray) -> None:
        """Reset worlds: no command yet, none timed out."""
        self.last_command[worlds] = np.inf
        self.timed_out[worlds] = False

    def check(self, sim: Contract, time: float) -> None:
        """Put the worlds that just went stale on safe commands, and say so."""
        if self.timeout is None:
            return
        stale = (time - self.last_command > self.timeout + 1e-9) & ~self.timed_out
        if not stale.any():
            return
        rows = np.flatnonzero(stale)
        self.timed_out[rows] = True
        hold_cols, hold_src, zero_cols = self._safe
        command = sim.command
        for c, s in zip(hold_cols, hold_src, strict=True):
            if self.free[c]:
                command[rows, c] = sim.state[rows, s]
        for c in zero_cols:
            if self.free[c]:
                command[rows, c] = 0.0
        names = ", ".join(self.namespaces[w] for w in rows[:8]) + (" ..." if len(rows) > 8 else "")
        self.warn(
            "timeout",
            f"{names}: no command for {self.timeout:g} s (command timeout); holding position, zero velocity and effort",
        )


def safe_plan(sim: Contract) -> tuple[list[int], list[int], list[int]]:
    """Where each command goes on a command timeout: position interfaces to the measured
    joint position (state column), velocity and effort to zero."""
    spec = sim.spec
    column = {name: i for i, name in enumerate(spec.state_interfaces)}
    hold_cols, hold_src, zero_cols = [], [], []
    for c, cmd in enumerate(spec.commands):
        if cmd.kind is InterfaceKind.POSITION:
            src = column.get(f"{cmd.joint}/position") if cmd.joint else None
            if src is not None:  # a position actuator without a measured joint holds its command
                hold_cols.append(c)
                hold_src.append(src)
        else:
            zero_cols.append(c)
    return hold_cols, hold_src, zero_cols
