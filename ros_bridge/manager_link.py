"""The loop's side of every world's controller_manager services. No rclpy here.

The workers answer list_controllers, list_hardware_interfaces and list_controller_types
from the plan (ManagerSpec) and from which controllers are active in each world
(protocol/active.py), which this module keeps equal to the ControllerManager's masks. switch_controller comes
through a worker's ring as a SWITCH request; `switch` carries it out between two
periods and says what to answer.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from batchsim.contract import Contract
from batchsim.controllers import ControllerManager
from batchsim.memory import Memory
from ros_bridge.protocol.active import ActiveWriter
from ros_bridge.protocol.requests import decode_document, decode_switch


@dataclasses.dataclass(frozen=True)
class ControllerSpec:
    """One controller as controller_manager's ListControllers shows it (the static part).

    Attributes:
      name, type: the YAML's name and plugin name.
      command_interfaces: the command interfaces it claims while active.
      state_interfaces: the state interfaces it reads.
      update_rate: Hz.
      parameters: its parameters (ControllerInfo.parameters), which its node holds.
      runtime: those it takes at run time, with their values at start (ControllerInfo.runtime).
    """

    name: str
    type: str
    command_interfaces: tuple[str, ...]
    state_interfaces: tuple[str, ...]
    update_rate: int
    parameters: tuple[tuple[str, Any], ...] = ()
    runtime: tuple[tuple[str, Any], ...] = ()


@dataclasses.dataclass(frozen=True)
class ManagerScope:
    """One controller_manager of a world: the world's own (`prefix` ""), or in a world of several
    robots (batchsim.fleet) each robot's, at `<ns>/<robot>/controller_manager`, which shows and
    switches that robot's controllers and interfaces by the names the robot gives them.

    Attributes:
      prefix: `<robot>/`, or "" for a world of one robot.
      hardware: its hardware component's name (the robot's, else the model's).
      controllers: indices into ManagerSpec.controllers (and `cm.active`'s columns).
      command_interfaces, state_interfaces: its interfaces, by the world's names.
    """

    prefix: str
    hardware: str
    controllers: tuple[int, ...]
    command_interfaces: tuple[str, ...]
    state_interfaces: tuple[str, ...]

    def local(self, name: str) -> str:
        """A world name as this scope's clients see it."""
        return name.removeprefix(self.prefix)


@dataclasses.dataclass(frozen=True)
class ManagerSpec:
    """What every world's `<ns>/controller_manager/...` services serve
    (ros_bridge/worker/controller_manager.py). Which controller is active in which world
    lives in shared memory (`cm.active`, (nworld, ncontroller)), written by the loop.

    Attributes:
      controllers: in the YAML's order.
      types: (plugin name, base class) of every controller type batchsim can load.
      command_interfaces, state_interfaces: the system's.
      hardware: the hardware component's name (the `<ros2_control>` block's, else the model's).
      scopes: the controller_managers every world serves: one, or one per robot (ManagerScope).
      update_rate: the controller_manager's own `update_rate` (Hz), else the control rate.
    """

    controllers: tuple[ControllerSpec, ...]
    types: tuple[tuple[str, str], ...]
    command_interfaces: tuple[str, ...]
    state_interfaces: tuple[str, ...]
    hardware: str
    scopes: tuple[ManagerScope, ...] = ()
    update_rate: int = 0


def manager_spec(sim: Contract, manager: ControllerManager, control_rate: float) -> ManagerSpec:
    controllers = tuple(
        ControllerSpec(
            c.name,
            c.type,
            c.command_interfaces,
            c.state_interfaces,
            int(round(c.update_rate if c.update_rate else control_rate)),
            c.parameters,
            c.runtime,
        )
        for c in manager.describe()
    )
    spec = sim.spec
    if spec.robots:
        scopes = tuple(
            ManagerScope(
                r.prefix,
                r.name,
                tuple(k for k, c in enumerate(controllers) if c.name.startswith(r.prefix)),
                tuple(spec.command_interfaces[c] for c in r.commands),
                tuple(spec.state_interfaces[c] for c in r.state),
            )
            for r in spec.robots
        )
    else:
        scopes = (
            ManagerScope(
                "", spec.name, tuple(range(len(controllers))), tuple(spec.command_interfaces), tuple(spec.state_interfaces)
            ),
        )
    return ManagerSpec(
        controllers=controllers,
        types=tuple(manager.controller_types()),
        command_interfaces=tuple(spec.command_interfaces),
        state_interfaces=tuple(spec.state_interfaces),
        hardware=spec.name,
        scopes=scopes,
        update_rate=int(round(manager.update_rate or control_rate)),
    )


class ManagerLink:
    """Keeps the shared active masks (protocol/active.py) equal to `manager`'s; carries out
    switch requests, parameter sets, goal cancels and gripper goals, and tells `tap` of each (a
    recording that keeps the controllers' inputs: ros_bridge/input_recording.py; None: nobody).

    Args:
      manager: the controllers.
      memory: the bridge's shared memory.
      world_names: per world, its name for messages (the namespace).
    """

    def __init__(self, manager: ControllerManager, memory: Memory, world_names: list[str]):
        self.manager = manager
        self.tap: Any = None
        self.active = ActiveWriter(memory)
        self.names = [c.name for c in manager]
        self.world_names = world_names
        for k, name in enumerate(self.names):
            self.active.set(k, slice(None), manager.active(name))

    def switch(self, payload: np.ndarray) -> tuple[int, int, bool, str]:
        """A SWITCH request: (ticket, world, ok, message) to answer with."""
        ticket, world, activate, deactivate, strictness, asap = decode_switch(payload)
        self._tell("switch", world, activate=list(activate), deactivate=list(deactivate), strictness=strictness, asap=asap)
        try:
            result = self.manager.switch(np.array([world]), activate, deactivate, strictness, asap)
        except ValueError as e:  # an unknown strictness
            return ticket, world, False, str(e)
        index = {n: k for k, n in enumerate(self.names)}
        for name, worlds in result.deactivated.items():
            self.active.set(index[name], worlds, False)
        for name, worlds in result.activated.items():
            self.active.set(index[name], worlds, True)
        return ticket, world, result.ok, result.message

    def set_parameters(self, payload: np.ndarray) -> tuple[int, bool, str]:
        """A SET_PARAMETERS request (a controller node's set_parameters): (ticket, ok, message)."""
        ticket, world, document = decode_document(payload)
        name = document.get("controller")
        if name not in self.names:
            return ticket, False, f"no controller named {name!r}"
        self._tell("parameters", world, controller=name, values=document.get("values", {}))
        why = self.manager[name].set_parameters(np.array([world]), document.get("values", {}))
        return ticket, not why, why

    def cancel(self, controller: str, world: int, goal: int) -> None:
        """A goal's cancel, to its controller."""
        self._tell("cancel", world, controller=controller, goal=int(goal))
        self.manager[controller].cancel(np.array([world]), np.array([goal]))

    def gripper_goal(self, controller: str, world: int, goal: int, position: float, max_effort: float) -> list:
        """A GripperCommand goal, to its controller: its refusals."""
        self._tell("gripper", world, controller=controller, goal=int(goal), position=float(position), max_effort=float(max_effort))
        return self.manager[controller].set_goals(np.array([world]), np.array([goal]), np.array([position]), np.array([max_effort]))

    def _tell(self, kind: str, world: int, **what: Any) -> None:
        if self.tap is not None:
            self.tap.control(kind, int(world), what)
