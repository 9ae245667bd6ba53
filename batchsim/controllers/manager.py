"""ros2_control's controller_manager over every world: a SimLoop participant.

Every controller runs vectorized over all worlds, but is active or inactive per world, as
if each world had its own controller_manager. `switch` is controller_manager's
`switch_controller` (controller_manager_msgs/srv/SwitchController) applied to a list of
worlds; `describe`, `hardware_interfaces` and `controller_types` are the data behind
ListControllers, ListHardwareInterfaces and ListControllerTypes. Nothing here knows ROS:
the bridge turns these into services.

    manager.switch([5], activate=["forward_position_controller"],
                   deactivate=["joint_trajectory_controller"], strictness=Strictness.STRICT)
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Sequence
from typing import Any

import numpy as np

from batchsim.controllers.base import Controller
from batchsim.controllers.types import CONTROLLER_TYPES
from batchsim.loop import Participant
from batchsim.model import RobotSpec
from batchsim.types import AnyCase, worlds_index

#: every batchsim controller is a plain (not chainable) ros2_control controller
CONTROLLER_BASE_CLASS = "controller_interface::ControllerInterface"


class Strictness(AnyCase, enum.IntEnum):
    """SwitchController's strictness, by number or name (any case); jazzy treats AUTO and
    FORCE_AUTO (and 0) as BEST_EFFORT."""

    BEST_EFFORT = 1
    STRICT = 2

    @classmethod
    def _missing_(cls, value: object) -> Strictness | None:
        if value in (0, 3, 4):  # unset (the default parameter is best_effort), AUTO, FORCE_AUTO
            return cls.BEST_EFFORT
        return super()._missing_(value)


@dataclasses.dataclass(frozen=True)
class SwitchResult:
    """What `switch` did, as SwitchController's response plus the details.

    Attributes:
      ok: the response's `ok`: False when a STRICT request failed (nothing changed), an
        interface conflict refused the request, or a list named only unknown controllers.
      message: the response's `message`, one line per problem, ros2_control's wording.
      activated: controller -> (n,) intp, the worlds where it became active.
      deactivated: controller -> (n,) intp, the worlds where it became inactive.
      started, stopped: the command interfaces that started / stopped being claimed by any
        world's active controller, as passed to the system's perform_command_mode_switch.
    """

    ok: bool
    message: str = ""
    activated: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    deactivated: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    started: tuple[str, ...] = ()
    stopped: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class ControllerInfo:
    """One controller as ListControllers reports it.

    Attributes:
      name, type: the YAML's name and plugin name (`joint_trajectory_controller/JointTrajectoryController`).
      command_interfaces: the command interfaces it claims when active.
      state_interfaces: the state interfaces it reads.
      update_rate: its own `update_rate` parameter, else the manager's (Hz; None: neither set).
      is_async: always False: every controller runs in the loop thread.
      active: (nworld,) bool, a copy: the worlds where it is active.
      parameters: its `ros__parameters` as the YAML gives them, flattened (`gains.joint1.p`), sorted.
      runtime: those it takes at run time (Controller.set_parameters), as at start, defaults included.
    """

    name: str
    type: str
    command_interfaces: tuple[str, ...]
    state_interfaces: tuple[str, ...]
    update_rate: float | None
    is_async: bool
    active: np.ndarray
    parameters: tuple[tuple[str, Any], ...] = ()
    runtime: tuple[tuple[str, Any], ...] = ()

    def state(self, world: int) -> str:
        """The lifecycle state name in one world: `active` or `inactive`."""
        return "active" if self.active[world] else "inactive"


@dataclasses.dataclass(frozen=True)
class InterfaceInfo:
    """One hardware interface in one world, as ListHardwareInterfaces reports it.

    `claimed_by` names the active controller that claims it ("" if none); state interfaces
    are never claimed.
    """

    name: str
    is_available: bool
    is_claimed: bool
    claimed_by: str = ""


@dataclasses.dataclass(frozen=True)
class HardwareInterfaces:
    """ListHardwareInterfaces' response for one world."""

    command_interfaces: tuple[InterfaceInfo, ...]
    state_interfaces: tuple[InterfaceInfo, ...]


class ControllerManager(Participant):
    """ros2_control's controller_manager over every world: a SimLoop participant.

    `update(sim, time, period)` runs every controller that is active in some world, in the
    YAML's order, between the loop's read() and write(); controllers write only the command
    columns they claim. In a world where a controller is inactive its claimed command
    columns keep the value they had (ros2_control leaves the last command): the controller
    still computes every world, and the manager puts those worlds' columns back after it.
    A fully active fleet pays nothing for this. A controller inactive in every world is not
    updated at all.

    A controller inactive in a world still accepts inputs for it (a trajectory, a command):
    they move nothing, and activation drops them. The bridge should drop them at the edge,
    as ros2_controllers do (JTC ignores topic messages and rejects action goals while
    inactive), by consulting `active(name)`.

    `on_reset(sim, worlds)` (SimLoop.reset's hook) tells every controller that worlds were
    reset: they drop their goals and hold the reset pose; activation is kept. Nothing is
    inferred from the state: a world whose time goes backwards is not taken for a reset.

    Threading: call `switch` from the loop thread (between periods, e.g. from a request
    queue drained by a participant); it is not locked. Its bookkeeping (`active`, claims)
    changes at once; its effects on the controllers (reset of the switched worlds, the
    system's perform_command_mode_switch) happen at the start of the next `update`.

    Attributes:
      update_rate: the controller_manager's update_rate (Hz), or None if the YAML has none.
      controllers: name -> Controller, in the YAML's order.
      claimed: the command interfaces held by a controller active at load.
      owner: command interface -> the controller that held it at load.
      warnings: one line per parameter that was ignored (unknown to the stock controller),
        and per controller that starts inactive because another holds its interface.
      source: the YAML file's name, for messages.
    """

    def __init__(
        self,
        controllers: Sequence[Controller],
        *,
        update_rate: float | None = None,
        source: str = "controllers",
        warnings: Sequence[str] = (),
        spec: RobotSpec | None = None,
        types: dict[str, type[Controller]] | None = None,
    ):
        self.controllers = {c.name: c for c in controllers}
        self.update_rate = update_rate
        self.source = source
        self.warnings = list(warnings)
        self.spec = spec if spec is not None or not controllers else controllers[0].spec
        self._types = types
        self._list = list(self.controllers.values())
        self._index = {c.name: k for k, c in enumerate(self._list)}
        self.nworld = max((c.nworld for c in self._list), default=0)
        self._command_names = list(self.spec.command_interfaces) if self.spec is not None else []
        column = {n: k for k, n in enumerate(self._command_names)}
        self._cols = [np.array([column[i] for i in c.command_interfaces], dtype=np.intp) for c in self._list]
        # per controller: (nworld,) active; per world and command column: the active holder (-1: none)
        self._active = np.ones((len(self._list), self.nworld), bool)
        self._holder = np.full((self.nworld, len(self._command_names)), -1, np.intp)
        owner: dict[str, str] = {}
        for k, c in enumerate(self._list):
            taken = [i for i in c.command_interfaces if i in owner]
            if taken:  # ros2_control loads both and activates one: the first in the YAML
                self._active[k] = False
                self.warnings.append(
                    f"{source}: controller {c.name!r} starts inactive: its command interface "
                    f"{taken[0]!r} is claimed by {owner[taken[0]]!r}; activate it with switch_controller"
                )
                continue
            for i in c.command_interfaces:
                owner[i] = c.name
            self._holder[:, self._cols[k]] = k
        self.claimed = frozenset(owner)
        self.owner = owner
        self._activated = False
        self._pending: list[tuple[dict[int, np.ndarray], dict[int, np.ndarray], list[str], list[str]]] = []
        self._plan: list[tuple[Controller, np.ndarray | None, np.ndarray]] = []
        self._replan()

    # --- lookup ---
    def __getitem__(self, name: str) -> Controller:
        try:
            return self.controllers[name]
        except KeyError:
            raise KeyError(
                f"no controller named {name!r}; controllers: {', '.join(self.controllers)}"
            ) from None

    def __iter__(self):
        return iter(self.controllers.values())

    def __len__(self) -> int:
        return len(self.controllers)

    def of_type(self, cls: type) -> list[Controller]:
        return [c for c in self.controllers.values() if isinstance(c, cls)]

    def active(self, name: str) -> np.ndarray:
        """(nworld,) bool, where controller `name` is active: a read-only view that follows
        later switches (copy it to keep a snapshot). KeyError for an unknown name."""
        self[name]
        view = self._active[self._index[name]].view()
        view.flags.writeable = False
        return view

    # --- the loop ---
    def update(self, sim: Any, time: float, period: float) -> None:
        if not self._activated:  # the first period: every controller holds where the robot is
            switch = getattr(sim, "perform_command_mode_switch", None)
            held = self._held()
            if switch is not None and held:  # the claimed interfaces drive their actuators
                switch(held)
            for c in self._list:
                c.time = time
                c.activate(sim, time)
            self._activated = True
        if self._pending:
            self._apply_pending(sim, time)
        for c, rows, cols in self._plan:
            c.time = time
            if rows is None:
                c.update(sim, time, period)
            else:  # inactive in `rows`: those worlds' claimed columns keep their value
                where = np.ix_(rows, cols)
                kept = sim.command[where]
                c.update(sim, time, period)
                sim.command[where] = kept

    def while_stepping(self, sim: Any, time: float, period: float) -> None:
        """While the device steps the period from `time` (SimLoop): each running controller's
        work for the next update done ahead (Controller.prepare)."""
        for c, _, _ in self._plan:
            c.prepare(time + period)

    def on_reset(self, sim: Any, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """The listed worlds (None: all) were reset: every controller drops their goals.

        SimLoop.reset calls it; so must anything else that resets worlds under the manager.
        """
        rows = _ascending(worlds, sim.nworld)
        for c in self.controllers.values():
            c.reset(sim, rows)

    def reset_robot(self, sim: Any, robot: str, worlds: Sequence[int] | np.ndarray) -> None:
        """One robot of a world of several was reset alone in the listed worlds
        (batchsim.fleet.reset): its controllers (`<robot>/...`) drop their goals there; the other
        robots' run on."""
        rows = _ascending(worlds, sim.nworld)
        for name, c in self.controllers.items():
            if name.startswith(f"{robot}/"):
                c.reset(sim, rows)

    def _replan(self) -> None:
        """What update runs: (controller, its inactive worlds or None, its claimed columns)."""
        plan = []
        for k, c in enumerate(self._list):
            mask = self._active[k]
            if mask.all():
                plan.append((c, None, self._cols[k]))
            elif mask.any():
                # a controller claiming nothing has no columns to keep: it just runs
                plan.append((c, np.flatnonzero(~mask) if len(self._cols[k]) else None, self._cols[k]))
        self._plan = plan

    def _held(self) -> list[str]:
        """The command interfaces an active controller claims in some world."""
        held = (self._holder >= 0).any(axis=0)
        return [self._command_names[j] for j in np.flatnonzero(held)]

    def _apply_pending(self, sim: Any, time: float) -> None:
        switch = getattr(sim, "perform_command_mode_switch", None)
        for activated, deactivated, start, stop in self._pending:
            # both hold where the robot is: deactivated ones drop their goals, activated
            # ones start from the current state (what they were sent while inactive is dropped)
            for k, rows in deactivated.items():
                self._list[k].time = time
                self._list[k].deactivate(sim, rows)
            for k, rows in activated.items():
                self._list[k].time = time
                self._list[k].reset(sim, rows)
            if switch is not None and (start or stop):
                switch(start, stop)
        self._pending.clear()

    # --- switch_controller ---
    def switch(
        self,
        worlds: Sequence[int] | np.ndarray | None,
        activate: Sequence[str] = (),
        deactivate: Sequence[str] = (),
        strictness: Strictness | int | str = Strictness.BEST_EFFORT,
        activate_asap: bool = False,
    ) -> SwitchResult:
        """controller_manager's switch_controller in the listed worlds (None: every world).

        Deactivates `deactivate` and activates `activate` in one step, as ros2_control
        does (jazzy's controller_manager.cpp), per world:

        - an unknown name: STRICT fails and changes nothing; BEST_EFFORT drops it (and
          fails, as upstream, if a non-empty list names no known controller);
        - activating a controller already active in a world (and not also deactivated),
          or deactivating one inactive there: STRICT fails; BEST_EFFORT skips those worlds;
        - a controller in both lists is restarted where it is active;
        - activating a controller whose command interface stays claimed by another active
          controller, or is claimed by another one being activated: STRICT fails naming the
          interface, the world and both controllers; BEST_EFFORT skips that controller in
          those worlds (upstream refuses the whole request; per world, skipping is kinder);
        - deactivate and activate in one request move the claimed interfaces between
          controllers; the system's perform_command_mode_switch(start, stop) gets the
          interfaces that start / stop being claimed anywhere in the fleet (its mode is
          fleet-wide), at the start of the next update.

        `activate_asap` is accepted and changes nothing: the hardware is always ready.
        Call it from the loop thread; it takes effect at the start of the next `update`.

        Raises:
          ValueError: a world out of range, or an unknown strictness (the caller's bug).
        """
        del activate_asap
        strict = Strictness(strictness) is Strictness.STRICT
        rows = self._worlds(worlds)
        problems: list[str] = []

        def known(names: Sequence[str], action: str) -> list[int] | None:
            found = []
            for name in names:
                if name in self._index:
                    if self._index[name] not in found:
                        found.append(self._index[name])
                    continue
                problems.append(
                    f"Could not {action} controller with name '{name}' because no controller with "
                    "this name exists"
                )
                if strict:
                    return None
            return found

        stop_k, start_k = known(deactivate, "deactivate"), known(activate, "activate")
        if stop_k is None or start_k is None:
            return SwitchResult(False, problems[-1] + "; no controller is switched (STRICT)")
        if (deactivate and not stop_k) or (activate and not start_k):
            return SwitchResult(False, "\n".join(problems))

        def where(mask: np.ndarray) -> str:
            w = rows[mask]
            return f"world {w[0]}" if len(w) == 1 else f"worlds {w.tolist()}"

        # per controller: the worlds (of `rows`) where it is deactivated / activated
        off: dict[int, np.ndarray] = {}
        for k in stop_k:
            on_now = self._active[k, rows]
            if not on_now.all():
                problems.append(
                    f"Controller with name '{self._list[k].name}' can not be deactivated since it is "
                    f"not active in {where(~on_now)}"
                )
                if strict:
                    return self._refused(problems)
            if on_now.any():
                off[k] = on_now
        holder = self._holder[rows].copy()  # the claims once the deactivations are done
        for k, mask in off.items():
            cols = self._cols[k]
            sub = holder[:, cols]
            sub[mask[:, None] & (sub == k)] = -1
            holder[:, cols] = sub
        on: dict[int, np.ndarray] = {}
        for k in start_k:
            c = self._list[k]
            mask = ~self._active[k, rows] | off.get(k, np.zeros(len(rows), bool))
            if not mask.all():
                problems.append(f"Controller with name '{c.name}' is already active in {where(~mask)}")
                if strict:
                    return self._refused(problems)
            cols = self._cols[k]
            if len(cols):
                others = holder[:, cols]
                busy = mask[:, None] & (others >= 0) & (others != k)
                if busy.any():
                    r, j = np.argwhere(busy)[0]
                    other = int(others[r, j])
                    by = "is being activated" if other in on else "stays active"
                    problems.append(
                        f"Unable to activate controller '{c.name}' since the command interface "
                        f"'{c.command_interfaces[j]}' is claimed by controller '{self._list[other].name}', "
                        f"which {by}, in {where(busy.any(axis=1))}"
                    )
                    if strict:
                        return self._refused(problems)
                    mask = mask & ~busy.any(axis=1)
                sub = holder[:, cols]
                sub[mask] = k
                holder[:, cols] = sub
            if mask.any():
                on[k] = mask
        if not off and not on:
            problems.append(
                "After checking the controllers, no controllers need to be activated or deactivated."
            )
            return SwitchResult(True, "\n".join(problems))

        # commit: the bookkeeping now, the controllers' side at the next update
        before = (self._holder >= 0).any(axis=0)
        for k, mask in off.items():
            self._active[k, rows[mask]] = False
        for k, mask in on.items():
            self._active[k, rows[mask]] = True
        self._holder[rows] = holder
        after = (self._holder >= 0).any(axis=0)
        started = [self._command_names[j] for j in np.flatnonzero(after & ~before)]
        stopped = [self._command_names[j] for j in np.flatnonzero(before & ~after)]
        deactivated = {k: rows[m] for k, m in off.items()}
        activated = {k: rows[m] for k, m in on.items()}
        self._pending.append((activated, deactivated, started, stopped))
        self._replan()
        return SwitchResult(
            True,
            "\n".join(problems),
            activated={self._list[k].name: w for k, w in activated.items()},
            deactivated={self._list[k].name: w for k, w in deactivated.items()},
            started=tuple(started),
            stopped=tuple(stopped),
        )

    def _refused(self, problems: list[str]) -> SwitchResult:
        return SwitchResult(False, problems[-1] + "; no controller is switched (STRICT)")

    def _worlds(self, worlds: Sequence[int] | np.ndarray | None) -> np.ndarray:
        return _ascending(worlds, self.nworld)

    # --- queries, as plain data for the ROS services ---
    def describe(self) -> list[ControllerInfo]:
        """Every controller, in the YAML's order, as ListControllers reports it."""
        out = []
        for k, c in enumerate(self._list):
            rate = c.params.values.get("update_rate")
            own = isinstance(rate, int | float) and not isinstance(rate, bool) and rate > 0
            out.append(
                ControllerInfo(
                    name=c.name,
                    type=c.TYPE,
                    command_interfaces=tuple(c.command_interfaces),
                    state_interfaces=tuple(c.state_interfaces),
                    update_rate=float(rate) if own else self.update_rate,
                    is_async=False,
                    active=self._active[k].copy(),
                    parameters=tuple(sorted(c.params.values.items())),
                    runtime=tuple(c.runtime_parameters().items()),
                )
            )
        return out

    def hardware_interfaces(self, world: int) -> HardwareInterfaces:
        """The system's interfaces in one world: each command interface with the active
        controller that claims it there, and the state interfaces (never claimed)."""
        if not 0 <= world < self.nworld:
            raise ValueError(f"world {world} is out of range: worlds are 0..{self.nworld - 1}")
        holders = self._holder[world]
        command = tuple(
            InterfaceInfo(
                n, True, bool(holders[j] >= 0), self._list[holders[j]].name if holders[j] >= 0 else ""
            )
            for j, n in enumerate(self._command_names)
        )
        names = self.spec.state_interfaces if self.spec is not None else []
        return HardwareInterfaces(command, tuple(InterfaceInfo(n, True, False) for n in names))

    def controller_types(self) -> list[tuple[str, str]]:
        """(plugin name, base class name) of every controller type the YAML may name."""
        types = CONTROLLER_TYPES if self._types is None else self._types
        return [(name, CONTROLLER_BASE_CLASS) for name in types]


def _ascending(worlds: Sequence[int] | np.ndarray | None, nworld: int) -> np.ndarray:
    """The listed worlds (batchsim.types.worlds_index; None: every world) in ascending order,
    as switch reports them and the controllers' reset gets them."""
    rows = worlds_index(worlds, nworld)
    return np.arange(nworld) if rows is None else np.sort(rows)
