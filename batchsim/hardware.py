"""The contract: a batched mirror of ros2_control's `hardware_interface::SystemInterface`.

`SystemInterface` is the lifecycle alone, transition for transition as ros2_control's
`hardware_interface::System` drives it (UNKNOWN -> UNCONFIGURED -> INACTIVE -> ACTIVE,
FINALIZED; `on_init` ... `on_error` returning SUCCESS / FAILURE / ERROR). The table is
enforced here, once; an illegal transition raises `LifecycleError` naming the state.

`BatchedSystem` is the contract every backend honours, for `nworld` copies of one robot:

- `export_state_interfaces()` / `export_command_interfaces()`: ros2_control names.
- `state` `(nworld, nstate)` float64, refreshed by `read(time, period)`.
- `command` `(nworld, ncommand)` float64, applied by `write(time, period)` into `ctrl`;
  `write` does nothing unless ACTIVE.
- `step(nstep)`, `reset(worlds=None)`, `status` `(nworld,)` bitmask of `Status`,
  `sensordata[name]` `(nworld, dim)`, `time` `(nworld,)` float64 on every backend.

A world that fails (diverges, or overflows a buffer that cannot grow) is frozen, by one rule
on every backend: until `reset` lists it, it reads exactly what `read()` would have shown
just before the `step()` call in which it failed (state, base_state, sensordata, time),
and the failure is logged once, naming the world and the reason (`batchsim.failures`).

A backend subclasses `BatchedSystem` and implements the engine hooks (`_open`, `_close`,
`_ctrl_host`, `_upload_ctrl`, `_read`, `_step`, `_reset`, and `_park` where the engine
cannot skip a world); everything a user sees, checks and bookkeeping included, lives here
so that every backend behaves the same.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.failures import FailureLog, ensure_log_dir
from batchsim.model import RobotSpec, StateColumn, initial_command


class LifecycleState(enum.IntEnum):
    """Primary lifecycle states, with the ids of lifecycle_msgs/msg/State."""

    UNKNOWN = 0
    UNCONFIGURED = 1
    INACTIVE = 2
    ACTIVE = 3
    FINALIZED = 4


class CallbackReturn(enum.Enum):
    """What a lifecycle callback returns (rclcpp_lifecycle's CallbackReturn)."""

    SUCCESS = "success"
    FAILURE = "failure"
    ERROR = "error"


class ReturnType(enum.Enum):
    """What read() and write() return (hardware_interface::return_type)."""

    OK = 0
    ERROR = 1
    DEACTIVATE = 2


class Status(enum.IntFlag):
    """Per-world status bits. One bad world never stops the others."""

    OK = 0
    DIVERGED = 1  # NaN/inf or a MuJoCo instability warning: frozen until reset
    OVERFLOW = 2  # contact or constraint buffer overflow: frozen until reset
    BAD_COMMAND = 4  # the last write's command for this world was rejected, not applied


FROZEN = Status.DIVERGED | Status.OVERFLOW
_FROZEN_BITS = np.uint8(FROZEN)  # converted once: an IntFlag to uint8 costs microseconds per read()
MAX_COMMAND = 1e10  # MuJoCo's mjMAXVAL: a ctrl beyond it trips mjWARN_BADCTRL
#: the engine fields read() gathers state interfaces from (`StateColumn.source`), in this order
READ_FIELDS = ("qpos", "qvel", "qfrc_actuator", "sensordata")


class LifecycleError(RuntimeError):
    """A lifecycle transition or call that the current state does not allow."""


S = LifecycleState
R = CallbackReturn

# transition -> (states it starts from, callback, outcome -> next state).
# An outcome missing from the table (ERROR, and FAILURE where ros2_control says so) goes
# through error(), as in hardware_interface::System.
_TABLE: dict[str, tuple[frozenset[LifecycleState], str, dict[CallbackReturn, LifecycleState]]] = {
    "configure": (frozenset({S.UNCONFIGURED}), "on_configure", {R.SUCCESS: S.INACTIVE, R.FAILURE: S.UNCONFIGURED}),
    "cleanup": (frozenset({S.INACTIVE}), "on_cleanup", {R.SUCCESS: S.UNCONFIGURED}),
    "activate": (frozenset({S.INACTIVE}), "on_activate", {R.SUCCESS: S.ACTIVE, R.FAILURE: S.INACTIVE}),
    "deactivate": (frozenset({S.ACTIVE}), "on_deactivate", {R.SUCCESS: S.INACTIVE, R.FAILURE: S.ACTIVE}),
    "shutdown": (
        frozenset({S.UNCONFIGURED, S.INACTIVE, S.ACTIVE}),
        "on_shutdown",
        {R.SUCCESS: S.FINALIZED},
    ),
}


class SystemInterface:
    """ros2_control's hardware lifecycle. Subclasses override the `on_*` callbacks.

    Call the transitions (`initialize`, `configure`, `activate`, `deactivate`, `cleanup`,
    `shutdown`, `error`); each runs its callback and moves to the state the callback's
    result selects, and returns that state. A callback that raises counts as ERROR: the
    system goes through `on_error`, then the exception propagates.
    """

    def __init__(self) -> None:
        self._lifecycle = LifecycleState.UNKNOWN

    @property
    def lifecycle_state(self) -> LifecycleState:
        return self._lifecycle

    # --- callbacks (override) ---
    def on_init(self) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_cleanup(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_activate(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_deactivate(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_shutdown(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_error(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    # --- transitions ---
    def initialize(self) -> LifecycleState:
        """UNKNOWN -> UNCONFIGURED through on_init; FINALIZED if it fails."""
        self._require("initialize", frozenset({S.UNKNOWN}))
        try:
            result = self.on_init()
        except BaseException:
            self._lifecycle = S.FINALIZED
            raise
        self._lifecycle = S.UNCONFIGURED if result is R.SUCCESS else S.FINALIZED
        return self._lifecycle

    def configure(self) -> LifecycleState:
        return self._transition("configure")

    def cleanup(self) -> LifecycleState:
        return self._transition("cleanup")

    def activate(self) -> LifecycleState:
        return self._transition("activate")

    def deactivate(self) -> LifecycleState:
        return self._transition("deactivate")

    def shutdown(self) -> LifecycleState:
        return self._transition("shutdown")

    def error(self) -> LifecycleState:
        """Run on_error: UNCONFIGURED if it handles the error, else FINALIZED."""
        self._require("error", frozenset(set(S) - {S.UNKNOWN, S.FINALIZED}))
        try:
            result = self.on_error(self._lifecycle)
        except BaseException:
            self._lifecycle = S.FINALIZED
            raise
        self._lifecycle = S.UNCONFIGURED if result is R.SUCCESS else S.FINALIZED
        return self._lifecycle

    def _transition(self, name: str) -> LifecycleState:
        allowed, callback, outcomes = _TABLE[name]
        self._require(name, allowed)
        previous = self._lifecycle
        try:
            result = getattr(self, callback)(previous)
        except BaseException:
            self.error()
            raise
        if result in outcomes:
            self._lifecycle = outcomes[result]
        else:
            self.error()
        return self._lifecycle

    def _require(self, what: str, allowed: frozenset[LifecycleState]) -> None:
        if self._lifecycle not in allowed:
            names = " or ".join(sorted(s.name for s in allowed))
            raise LifecycleError(
                f"cannot {what}: the system is {self._lifecycle.name}, and {what} needs {names}"
            )


class SensorData(Mapping[str, np.ndarray]):
    """Every MJCF sensor by name: `sim.sensordata["wrist_force"]` is `(nworld, dim)`."""

    def __init__(self, views: dict[str, np.ndarray]):
        self._views = views

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self._views[name]
        except KeyError:
            raise KeyError(f"no sensor named {name!r}; sensors: {', '.join(self._views)}") from None

    def __iter__(self):
        return iter(self._views)

    def __len__(self) -> int:
        return len(self._views)


@dataclasses.dataclass
class StepFailures:
    """The worlds that failed during one `_step(nstep)` call, as a backend reports them.

    Attributes:
      worlds: (k,) int64, the worlds; none of them was frozen before the call.
      status: (k,) uint8, their Status bits: DIVERGED and/or OVERFLOW.
      reasons: k strings, why each failed (MuJoCo's warning text where there is one).
      readings: (k, ncolumn) float64, their read() columns (`state`, then `base_state`) as
        they were at the start of the call.
      sensordata: (k, nsensordata) float64, likewise.
      time: (k,) float64, likewise.
    """

    worlds: np.ndarray
    status: np.ndarray
    reasons: list[str]
    readings: np.ndarray
    sensordata: np.ndarray
    time: np.ndarray


class BatchedSystem(SystemInterface):
    """`nworld` copies of one robot behind ros2_control's SystemInterface.

    Attributes (valid from on_configure on):
      nworld: number of worlds.
      state: (nworld, nstate) float64, the state interfaces, refreshed by read().
      command: (nworld, ncommand) float64, the command interfaces, applied by write().
      status: (nworld,) uint8 bitmask of Status, current after step() and write().
      time: (nworld,) float64 simulation time of each world, refreshed by read(); float64 on
        every backend (the GPU engines' own clocks are float32).
      sensordata: every MJCF sensor by name, (nworld, dim) each, refreshed by read().
      base_state: (nworld, 13) float64, the floating base (`spec.floating_base`) as MuJoCo's
        free joint holds it: position (3) and orientation quaternion (w, x, y, z) in the
        world frame, linear velocity (3) in the world frame, angular velocity (3) in the
        body frame; refreshed by read(), frozen with the rest of a frozen world's readings.
        None for a model without a floating base.
    """

    #: the registry name of the backend ("cpu", "mjx", "warp")
    name: ClassVar[str] = ""
    #: keyword options the backend's constructor takes, with their defaults
    OPTIONS: ClassVar[dict[str, Any]] = {}

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__()
        if int(nworld) != nworld or nworld < 1:
            raise ValueError(f"nworld must be a positive integer, got {nworld!r}")
        unknown = sorted(set(options) - set(self.OPTIONS))
        if unknown:
            known = ", ".join(self.OPTIONS) or "none"
            raise ValueError(f"unknown option {unknown[0]!r} for backend {self.name} (options: {known})")
        self.spec = spec
        self.nworld = int(nworld)
        self.options = {**self.OPTIONS, **options}
        self.reason = ""  # why this backend was chosen, for `batchsim info` and the status line
        m = spec.mjmodel
        self.model = m
        self.dt = float(m.opt.timestep)

        ncommand = len(spec.commands)
        # what read() gathers: the state interfaces, then the floating base's pose and twist
        self._columns = list(spec.state) + _base_columns(spec)
        self._bind_readings(np.zeros((self.nworld, len(self._columns))))
        self._command = np.zeros((self.nworld, ncommand))
        self.status = np.zeros(self.nworld, np.uint8)
        self.time = np.zeros(self.nworld)
        self._initial_command = initial_command(spec)
        self._command[:] = self._initial_command
        self._sensor_host = np.zeros((self.nworld, m.nsensordata))
        self.sensordata = SensorData(
            {s.name: self._sensor_host[:, s.adr : s.adr + s.dim] for s in spec.sensors}
        )
        # state columns gathered per source field: (state columns, field indices)
        self._gather: list[tuple[str, np.ndarray, np.ndarray]] = []
        for source in READ_FIELDS:
            cols = [i for i, c in enumerate(self._columns) if c.source == source]
            if cols:
                idx = [self._columns[i].index for i in cols]
                self._gather.append((source, _as_slice(cols), _as_slice(idx)))
        self._ctrl_index = np.array([c.actuator_id for c in spec.commands], dtype=np.intp)
        self._ctrl_cols = _as_slice(self._ctrl_index.tolist())  # a slice where it can be: faster
        self._opened = False
        # what frozen worlds show until reset: their readings from the start of the failing step()
        self._held_readings = np.zeros_like(self._readings)
        self._held_sensordata = np.zeros_like(self._sensor_host)
        self._held_time = np.zeros_like(self.time)
        self._none_frozen = np.zeros(self.nworld, bool)
        self._none_frozen.setflags(write=False)
        # whether the host readings are the engine's current values (read() since the last step())
        self._readings_current = False
        self._failure_log = FailureLog(self.name, self.nworld, mujoco_logs=self.name == "cpu")
        ensure_log_dir()  # MuJoCo's own log out of the working directory, unless placed already

    def _bind_readings(self, readings: np.ndarray) -> None:
        """Make `readings` (nworld, len(_columns)) the array read() fills; `state` and
        `base_state` are views of its columns."""
        nstate = len(self.spec.state)
        self._readings = readings
        self.state = readings[:, :nstate]
        self.base_state = readings[:, nstate:] if self.spec.floating_base is not None else None

    # --- interfaces ---
    def export_state_interfaces(self) -> list[str]:
        """State interface names, `"<joint>/<interface>"` and `"<sensor>/<field>"`, in column order."""
        return self.spec.state_interfaces

    def export_command_interfaces(self) -> list[str]:
        """Command interface names, `"<joint>/<interface>"`, in column order."""
        return self.spec.command_interfaces

    # --- lifecycle ---
    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        if self.spec.problems:
            raise ConfigurationError(f"{self.spec.name}: " + "; ".join(self.spec.problems))
        if not self._opened:
            self._open()
            self._opened = True
        self.reset()
        return CallbackReturn.SUCCESS

    def on_cleanup(self, previous_state: LifecycleState) -> CallbackReturn:
        self._release()
        return CallbackReturn.SUCCESS

    def on_shutdown(self, previous_state: LifecycleState) -> CallbackReturn:
        self._release()
        return CallbackReturn.SUCCESS

    def on_error(self, previous_state: LifecycleState) -> CallbackReturn:
        self._release()
        return CallbackReturn.SUCCESS

    def _release(self) -> None:
        if self._opened:
            self._close()
            self._opened = False

    # --- read / write ---
    def read(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """Refresh `state`, `base_state`, `sensordata` and `time` from the simulation (INACTIVE
        or ACTIVE). Frozen worlds show what they read before the step() in which they failed."""
        if self._lifecycle not in (S.INACTIVE, S.ACTIVE):
            return ReturnType.OK
        self._refresh()
        return ReturnType.OK

    def write(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """Apply `command` to every world's `ctrl`; a no-op unless ACTIVE.

        A world whose command row holds NaN, inf or a value beyond MAX_COMMAND gets
        BAD_COMMAND and keeps its previous `ctrl`; the other worlds are applied as usual.
        """
        if self._lifecycle is not S.ACTIVE:
            return ReturnType.OK
        command = self._command
        ctrl = self._ctrl_host()
        # MuJoCo itself zeroes ctrl beyond mjMAXVAL; reject it here, per world, with a status
        # bit. Fast path: two reductions, no temporaries (a NaN makes both comparisons fail).
        if command.size == 0 or (command.min() > -MAX_COMMAND and command.max() < MAX_COMMAND):
            ctrl[:, self._ctrl_cols] = command
            if self.status.any():
                self.status &= ~np.uint8(Status.BAD_COMMAND)
        else:
            good = (np.abs(command) < MAX_COMMAND).all(axis=1)
            rows = np.flatnonzero(good)
            ctrl[np.ix_(rows, self._ctrl_index)] = command[rows]
            self.status[good] &= ~np.uint8(Status.BAD_COMMAND)
            self.status[~good] |= np.uint8(Status.BAD_COMMAND)
        self._upload_ctrl()
        return ReturnType.OK

    @property
    def command(self) -> np.ndarray:
        """(nworld, ncommand) float64: the commands the next write() applies. Edit in place."""
        return self._command

    @command.setter
    def command(self, value: Any) -> None:
        self.set_command(value)

    def set_command(self, command: Any, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Copy `command` into `self.command` for all or the listed worlds; `(ncommand,)` broadcasts.

        `command` is `(nworld, ncommand)`, or `(len(worlds), ncommand)` with row i for
        `worlds[i]`, in the order given (a `(nworld,)` bool mask lists worlds in order).
        Raises ValueError naming the expected and actual shapes, a world out of range, or a
        world listed twice.
        """
        command = np.asarray(command, dtype=np.float64)
        rows = self._worlds(worlds)
        n = self.nworld if rows is None else len(rows)
        ncommand = len(self.spec.commands)
        if command.shape not in ((ncommand,), (n, ncommand)):
            raise ValueError(
                f"command must have shape ({n}, {ncommand}) or ({ncommand},), got {command.shape}"
                + (f"; command interfaces: {', '.join(self.spec.command_interfaces)}" if ncommand else "")
            )
        self._command[slice(None) if rows is None else rows] = command

    # --- stepping ---
    def step(self, nstep: int = 1) -> None:
        """Advance every world `nstep` physics steps; frozen (diverged, overflowed) worlds stay put.

        A world that fails during the call gets DIVERGED or OVERFLOW in `status`, is logged
        once (rate-limited over worlds) and is frozen: it reads as it did before this call
        until `reset` lists it.
        """
        self._require("step", frozenset({S.INACTIVE, S.ACTIVE}))
        if nstep < 1:
            raise ValueError(f"nstep must be >= 1, got {nstep}")
        self._failure_log.flush()
        failures = self._step(int(nstep))
        self._readings_current = False
        if failures is not None and failures.worlds.size:
            self._freeze(failures)

    def _freeze(self, failures: StepFailures) -> None:
        """Hold what the failed worlds read before the failing step, mark them, park them, say so."""
        worlds = failures.worlds
        self._held_readings[worlds] = failures.readings
        self._held_sensordata[worlds] = failures.sensordata
        self._held_time[worlds] = failures.time
        self.status[worlds] |= failures.status.astype(np.uint8)
        self._park(worlds)
        what = ["diverged" if s & Status.DIVERGED else "overflowed" for s in failures.status]
        self._failure_log.report(worlds, what, failures.reasons, failures.time)

    def reset(self, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset all worlds, or only the listed ones, to the initial state and command.

        Clears their status bits and refreshes `state`; no other world changes.
        """
        self._require("reset", frozenset({S.UNCONFIGURED, S.INACTIVE, S.ACTIVE}))
        if not self._opened:
            raise LifecycleError("cannot reset: the system is UNCONFIGURED; configure it first")
        rows = self._worlds(worlds)
        sel = np.arange(self.nworld) if rows is None else rows
        self.status[sel] = 0  # first: the engine's reset sees them unfrozen
        self._reset(rows)
        self._command[sel] = self._initial_command
        ctrl = self._ctrl_host()
        ctrl[sel] = self.spec.initial.ctrl
        ctrl[np.ix_(sel, self._ctrl_index)] = self._initial_command
        self._upload_ctrl()
        self._refresh()

    @property
    def frozen(self) -> np.ndarray:
        """(nworld,) bool: the worlds step() leaves alone until they are reset."""
        if not self.status.any():  # the usual case, on every read() and step(): no allocation
            return self._none_frozen
        return (self.status & _FROZEN_BITS) != 0

    def _worlds(self, worlds: Sequence[int] | np.ndarray | None) -> np.ndarray | None:
        """World indices as given, (k,) int64, in the caller's order; None for all.

        Raises ValueError for a world out of range, a world listed twice, or a mask of the
        wrong shape.
        """
        if worlds is None:
            return None
        rows = np.asarray(worlds)
        if rows.dtype == bool:
            if rows.shape != (self.nworld,):
                raise ValueError(f"a world mask must have shape ({self.nworld},), got {rows.shape}")
            return np.flatnonzero(rows)
        if rows.size and not np.issubdtype(rows.dtype, np.integer):
            raise ValueError(f"worlds must be integers or a ({self.nworld},) bool mask, got {rows.dtype}")
        rows = rows.astype(np.int64).reshape(-1)
        bad = rows[(rows < 0) | (rows >= self.nworld)]
        if bad.size:
            raise ValueError(f"world {bad[0]} is out of range: worlds are 0..{self.nworld - 1}")
        unique, counts = np.unique(rows, return_counts=True)
        if unique.size < rows.size:
            raise ValueError(f"world {unique[counts > 1][0]} is listed more than once")
        return rows

    def _refresh(self) -> None:
        """The engine's current readings into the host arrays, then frozen worlds' held ones."""
        self._read()
        self._readings_current = True
        if not self.status.any():  # the usual case: nothing held
            return
        frozen = self.frozen
        if frozen.any():
            self._readings[frozen] = self._held_readings[frozen]
            self._sensor_host[frozen] = self._held_sensordata[frozen]
            self.time[frozen] = self._held_time[frozen]

    def _gather_fields(
        self,
        fields: Mapping[str, np.ndarray],
        readings: np.ndarray,
        sensordata: np.ndarray,
        time: np.ndarray,
    ) -> None:
        """Host engine fields (`READ_FIELDS` `(nworld, ...)` and `time` `(nworld,)`) into
        readings `(nworld, ncolumn)`, sensordata `(nworld, nsensordata)` and time `(nworld,)`."""
        for source, cols, idx in self._gather:
            readings[:, cols] = fields[source][:, idx]
        sensordata[:] = fields["sensordata"]
        time[:] = fields["time"]

    # --- engine hooks, one set per backend ---
    def _open(self) -> None:
        """Allocate the engine and its buffers (on_configure)."""
        raise NotImplementedError

    def _close(self) -> None:
        """Free the engine (on_cleanup, on_shutdown, on_error)."""

    def _ctrl_host(self) -> np.ndarray:
        """The host (nworld, nu) float64 ctrl array that write() fills."""
        raise NotImplementedError

    def _upload_ctrl(self) -> None:
        """Make the host ctrl the engine's ctrl (a no-op where they are the same memory)."""

    def _read(self) -> None:
        """Every world's current values into `_readings` `(nworld, ncolumn)` (the columns of
        `_columns`), `_sensor_host` `(nworld, nsensordata)` and `time` `(nworld,)`, float64.
        Frozen worlds' rows are overwritten afterwards with what they hold."""
        raise NotImplementedError

    def _step(self, nstep: int) -> StepFailures | None:
        """Advance the unfrozen worlds nstep steps; report the worlds that failed in this call
        (None or an empty StepFailures: none). The base class then freezes them."""
        raise NotImplementedError

    def _reset(self, worlds: np.ndarray | None) -> None:
        """Reset the listed worlds (None: all) to `spec.initial`. Their status is already clear."""
        raise NotImplementedError

    def _park(self, worlds: np.ndarray) -> None:
        """Worlds just frozen: for an engine that steps every world whatever happens, keep them
        from costing the others anything (the GPU backends reset them and hold ctrl at zero).
        An engine that skips frozen worlds (cpu) has nothing to do."""


def _base_columns(spec: RobotSpec) -> list[StateColumn]:
    """The floating base's 7 qpos and 6 qvel entries as read columns (none without a base)."""
    base = spec.floating_base
    if base is None:
        return []
    pose = [StateColumn(f"{base.joint}/qpos{k}", "qpos", base.qposadr + k) for k in range(7)]
    twist = [StateColumn(f"{base.joint}/qvel{k}", "qvel", base.dofadr + k) for k in range(6)]
    return pose + twist


def _as_slice(index: list[int]) -> slice | np.ndarray:
    """An index list as a slice when it is an arithmetic progression (a view, not a gather)."""
    if not index:
        return np.array(index, dtype=np.intp)
    step = index[1] - index[0] if len(index) > 1 else 1
    if step > 0 and all(b - a == step for a, b in zip(index, index[1:], strict=False)):
        return slice(index[0], index[-1] + 1, step)
    return np.array(index, dtype=np.intp)


class ConfigurationError(ValueError):
    """The model or its ros2_control block asks for something the simulation cannot serve."""
