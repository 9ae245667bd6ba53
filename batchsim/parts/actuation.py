"""Between the command interfaces and `ctrl`: where ros2_control's hardware interface would
turn commands into actuator inputs, once per control period, for every world at once.

Most interfaces are copied straight into their actuator's ctrl. The rest, all declared in
the RobotSpec (`CommandInterface.mode`, `scale`, `offset`, `RobotSpec.mimics`):

- a gripper in control units: ctrl = scale * command + offset;
- a position or velocity interface on a torque motor: ctrl = PID(command - measured), the
  measurement being the joint's qpos / qvel as the last read() saw it, dt the simulated
  time since the world's previous write (`batchsim.pid`);
- a mimic joint's actuator: ctrl = multiplier * the mimicked joint's command + offset;
- several interfaces on one actuator (position and velocity PIDs on one motor): one is
  active at a time, as in ros2_control's `perform_command_mode_switch`; position first;
- a joint behind a transmission: its commands become its actuators' first
  (`batchsim.parts.transmissions.CommandMap`), and those go through the rules above.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from batchsim.model import CommandMode, RobotSpec, StateColumn
from batchsim.parts.transmissions import CommandMap
from batchsim.pid import PidBank
from batchsim.types import StateSource


class Actuation:
    """Commands -> ctrl for `nworld` worlds of `spec`.

    Attributes:
      trivial: every interface is a plain copy into its own actuator (write() keeps its fast path).
      active: (ncommand,) bool, the interfaces whose values reach ctrl.
      feedback_columns: what read() must gather for the PIDs (joint qpos / qvel), in order.
    """

    def __init__(self, spec: RobotSpec, nworld: int):
        self._map = CommandMap(spec)
        cmds = self._map.inner
        self.names = [c.name for c in spec.commands]
        self.nworld = nworld
        self._actuator = np.array([c.actuator_id for c in cmds], dtype=np.intp)
        self._scale = np.array([c.scale for c in cmds])
        self._offset = np.array([c.offset for c in cmds])
        self._pid = np.array([c.mode is not CommandMode.DIRECT for c in cmds], dtype=bool)
        self.active = np.ones(len(cmds), dtype=bool)
        seen: set[int] = set()
        for k, c in enumerate(cmds):  # commands come position first within an actuator
            if c.actuator_id in seen:
                self.active[k] = False
            seen.add(c.actuator_id)
        self._default_active = self.active.copy()
        shared = len(seen) < len(cmds)
        plain = bool((self._scale == 1.0).all() and (self._offset == 0.0).all())
        self.trivial = plain and not shared and not self._pid.any() and not spec.mimics and self._map.identity
        pid_cols = np.flatnonzero(self._pid)
        self._pid_cols = pid_cols
        self.feedback_columns = [
            StateColumn(
                f"{cmds[k].name}/measured",
                StateSource.QPOS if cmds[k].mode is CommandMode.POSITION_PID else StateSource.QVEL,
                cmds[k].qposadr if cmds[k].mode is CommandMode.POSITION_PID else cmds[k].dofadr,
            )
            for k in pid_cols
        ]
        self._bank = PidBank([cmds[k].pid for k in pid_cols], nworld) if len(pid_cols) else None
        self._last_time = np.full(nworld, np.nan)
        index = {name: k for k, name in enumerate(self.names)}  # mimics follow the commands themselves
        self._mimic_src = np.array([index[mc.source] for mc in spec.mimics], dtype=np.intp)
        self._mimic_act = np.array([mc.actuator_id for mc in spec.mimics], dtype=np.intp)
        self._mimic_mul = np.array([mc.multiplier for mc in spec.mimics])
        self._mimic_off = np.array([mc.offset for mc in spec.mimics])
        self._index()

    def _index(self) -> None:
        direct = np.flatnonzero(self.active & ~self._pid)
        self._direct = direct
        self._direct_act = self._actuator[direct]
        self._pid_active = self.active[self._pid_cols]
        self._pid_act = self._actuator[self._pid_cols[self._pid_active]]

    def switch(self, start: Iterable[str], stop: Iterable[str] = ()) -> None:
        """Make the `start` interfaces the ones that drive their actuators (ros2_control's
        perform_command_mode_switch); `stop` ones stop driving theirs. Unknown names raise
        ValueError naming them."""
        start, stop = list(start), list(stop)
        unknown = [n for n in (*start, *stop) if n not in self.names]
        if unknown:
            raise ValueError(f"no command interface {unknown[0]!r}; interfaces: {', '.join(self.names)}")
        for name in stop:
            self.active[self._map.stands_for(name)] = False
        for name in start:
            for k in self._map.stands_for(name):
                self.active[self._actuator == self._actuator[k]] = False
                self.active[k] = True
                if self._bank is not None and self._pid[k]:
                    self._bank.reset_columns(np.flatnonzero(self._pid_cols == k))
        self._index()

    def apply(
        self,
        ctrl: np.ndarray,
        command: np.ndarray,
        feedback: np.ndarray,
        time: np.ndarray,
        rows: np.ndarray | None = None,
    ) -> None:
        """Write the ctrl of the listed worlds (None: all) from their commands.

        Args:
          ctrl: (nworld, nu) the host ctrl, written in place.
          command: (nworld, ncommand) the command interfaces.
          feedback: (nworld, len(feedback_columns)) the PIDs' measurements from the last read().
          time: (nworld,) each world's simulation time at the last read().
        """
        r = slice(None) if rows is None else rows
        given = command[r]
        cmd = self._map.apply(given)
        if len(self._direct):
            values = cmd[:, self._direct] * self._scale[self._direct] + self._offset[self._direct]
            _put(ctrl, rows, self._direct_act, values)
        if self._bank is not None:
            last = self._last_time[r]
            dt = np.where(np.isnan(last), 0.0, time[r] - last)
            u = self._bank.update(cmd[:, self._pid_cols] - feedback[r], dt, r)
            self._last_time[r] = time[r]
            if self._pid_active.any():
                _put(ctrl, rows, self._pid_act, u[:, self._pid_active])
        if len(self._mimic_src):
            _put(ctrl, rows, self._mimic_act, given[:, self._mimic_src] * self._mimic_mul + self._mimic_off)

    def reset(self, worlds: np.ndarray, ctrl: np.ndarray, command: np.ndarray) -> None:
        """The listed worlds were reset: their PIDs start afresh, and the direct interfaces'
        ctrl holds their (initial) command; PID-driven actuators keep the initial ctrl until
        the next write. A reset of every world also gives an actuator whose every interface a
        switch stopped its first one (position) again, as mujoco_ros2_control's reset does, so
        the reset pose is held; an actuator another interface drives keeps it."""
        if len(worlds) == self.nworld:
            driven = np.unique(self._actuator[self.active])
            idle = self._default_active & ~np.isin(self._actuator, driven)
            if idle.any():
                self.active |= idle
                self._index()
        if self._bank is not None:
            self._bank.reset(worlds)
            self._last_time[worlds] = np.nan
        if len(self._direct):
            cmd = self._map.apply(command[worlds])
            values = cmd[:, self._direct] * self._scale[self._direct] + self._offset[self._direct]
            _put(ctrl, worlds, self._direct_act, values)
        if len(self._mimic_src):
            given = command[worlds]
            _put(ctrl, worlds, self._mimic_act, given[:, self._mimic_src] * self._mimic_mul + self._mimic_off)


def _put(ctrl: np.ndarray, rows: np.ndarray | None, cols: np.ndarray, values: np.ndarray) -> None:
    if rows is None:
        ctrl[:, cols] = values
    else:
        ctrl[np.ix_(rows, cols)] = values
