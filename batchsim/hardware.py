"""The contract: a batched mirror of ros2_control's `hardware_interface::SystemInterface`.

`BatchedSystem` is the contract every backend honours, for `nworld` copies of one robot:

- `export_state_interfaces()` / `export_command_interfaces()`: ros2_control names.
- `state` `(nworld, nstate)` float64, refreshed by `read(time, period)`.
- `command` `(nworld, ncommand)` float64, applied by `write(time, period)` into `ctrl`;
  `write` does nothing unless ACTIVE.
- `step(nstep)`, `reset(worlds=None)`, `status` `(nworld,)` bitmask of `Status`,
  `sensordata[name]` `(nworld, dim)`, `time` `(nworld,)` float64 on every backend.
- `render(camera, worlds=None)` -> `(rgb (n, H, W, 3) uint8, depth (n, H, W) float32)`,
  `scan(lidar, worlds=None)` -> `(n, nray) float32`, `sensors` (batchsim.sensors): cameras,
  lidars and sensor noise; `true_state` / `true_sensordata` without the noise.
- `body_poses(worlds=None)` -> `(xpos (n, nbody, 3), xquat (n, nbody, 4) w, x, y, z)` float64, on demand;
  `body_poses_into(xpos_out, xquat_out, bodies)`: tf's per-period copy (batchsim.body_poses).
- `set_base_velocity(command, worlds=None)`: mujoco_ros2_control's BaseVelocityPlugin
  (batchsim.base_velocity); `apply_wrench(wrenches, worlds=None)`: its ExternalWrenchPlugin.
- `set_variation(variation)`, `world_params()`: per-world randomization (batchsim.varying);
  `device_state()`, `write_device(command)`: state and commands on the engine's device (batchsim.device_io).

A world that fails (diverges, or overflows a buffer that cannot grow) is frozen, by one rule on
every backend: until `reset` lists it, it reads the noise-free values `read()` would have shown
just before the `step()` call in which it failed (state, base_state, sensordata, time), with no
fresh sensor noise, and the failure is logged once, naming the world and why (batchsim.failures).

A backend subclasses `BatchedSystem` and implements the engine hooks (batchsim.engine: `_open`,
`_close`, `_ctrl_host`, `_upload_ctrl`, `_read`, `_step`, `_reset`, `_body_poses`, `_pose_rows`, `_qstate`,
`_set_qstate`, and `_park` where the engine cannot skip a world); everything a user sees,
checks and bookkeeping included, lives here so that every backend behaves the same.

Beside it: batchsim.lifecycle (ros2_control's lifecycle table), batchsim.types (enums, constants,
shaped records), batchsim.sensing (cameras, lidars, noise), batchsim.engine (the hooks).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from batchsim.actuation import Actuation
from batchsim.base_velocity import BaseDriving
from batchsim.body_poses import BodyPoses
from batchsim.device_io import DeviceIO
from batchsim.engine import EngineHooks, check_options
from batchsim.external_wrench import Wrenching
from batchsim.failures import FailureLog, ensure_log_dir
from batchsim.lifecycle import CallbackReturn, LifecycleError, LifecycleState, SystemInterface
from batchsim.model import RobotSpec, initial_command
from batchsim.readings import Finish, as_slice, layout
from batchsim.sensing import Sensing
from batchsim.sensors import SensorConfig, SensorSuite
from batchsim.types import (
    FROZEN,
    MAX_COMMAND,
    ConfigurationError,
    ReturnType,
    SensorData,
    StateSource,
    Status,
    StepFailures,
    check_nstep,
    worlds_index,
)
from batchsim.types import Frames as Frames  # re-exported here
from batchsim.types import PendingFrames as PendingFrames
from batchsim.varying import Varying

S = LifecycleState
_FROZEN_BITS = np.uint8(FROZEN)  # converted once: an IntFlag to uint8 costs microseconds per read()



class BatchedSystem(BaseDriving, BodyPoses, Wrenching, Sensing, Varying, DeviceIO, EngineHooks, SystemInterface):
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
      base_states: (nworld, nbase, 13) float64, every floating base so (`spec.floating_bases`:
        the model's own, or each robot's of a fleet's world), a view of the same readings.
    """

    #: the registry name of the backend ("cpu", "mjx", "warp")
    name: ClassVar[str] = ""
    #: keyword options the backend's constructor takes, with their defaults
    OPTIONS: ClassVar[dict[str, Any]] = {}
    #: the type of each option whose default is None (which also stays allowed): bool, int,
    #: float or str, or object for one the backend resolves itself (a device); every other option
    #: takes its default's type
    OPTION_TYPES: ClassVar[dict[str, type]] = {}
    #: the least value of the numeric options that have one
    OPTION_MINIMA: ClassVar[dict[str, float]] = {}
    #: whether one render or scan covers every world at the cost of any subset (one GPU launch)
    sensors_batched: ClassVar[bool] = False
    #: whether the first control period compiles (mjx) or captures (warp) the step's program:
    #: the command line runs one under a progress line before the run starts
    compiles_first_period: ClassVar[bool] = False
    #: whether the engine logs a world's failure itself (C MuJoCo's MUJOCO_LOG.TXT): the first line names it
    logs_failures: ClassVar[bool] = False
    #: whether MJCF torque sensors read what C MuJoCo's do (MJX's cfrc_int: 0 where C reads a motor's torque)
    reads_torque_sensors: ClassVar[bool] = True

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__()
        if int(nworld) != nworld or nworld < 1:
            raise ValueError(f"nworld must be a positive integer, got {nworld!r}")
        self.check_options(options)
        self.spec = spec
        self.nworld = int(nworld)
        self.options = {**self.OPTIONS, **options}
        self.reason = ""  # why this backend was chosen, for `batchsim info` and the status line
        m = spec.mjmodel
        self.model = m
        self.dt = float(m.opt.timestep)

        ncommand = len(spec.commands)
        # commands -> ctrl beyond a plain copy: PIDs on motors, scaled grippers, mimic joints
        self._actuation = Actuation(spec, self.nworld)
        # what read() gathers (batchsim.readings): the state interfaces, the floating base's pose
        # and twist, the actuator states not among them, the joint positions/velocities the PIDs measure
        feedback = self._actuation.feedback_columns
        self._columns, self._actuator_columns = layout(spec, feedback)
        self._nfeedback = len(feedback)
        self._bind_readings(np.zeros((self.nworld, len(self._columns))))
        self._command = np.zeros((self.nworld, ncommand))
        self.status = np.zeros(self.nworld, np.uint8)
        self.time = np.zeros(self.nworld)
        self._initial_command = initial_command(spec)
        self._command[:] = self._initial_command
        self._bind_sensordata(np.zeros((self.nworld, m.nsensordata)))
        # state columns gathered per source field: (state columns, field indices)
        self._gather: list[tuple[str, np.ndarray, np.ndarray]] = []
        for source in StateSource:
            cols = [i for i, c in enumerate(self._columns) if c.source is source]
            if cols:
                idx = [self._columns[i].index for i in cols]
                self._gather.append((source.value, as_slice(cols), as_slice(idx)))
        self._finish = Finish(spec, self._columns)
        self._ctrl_index = np.array([c.actuator_id for c in spec.commands], dtype=np.intp)
        self._ctrl_cols = as_slice(self._ctrl_index.tolist())  # a slice where it can be: faster
        self._opened = False
        # what frozen worlds show until reset: their readings from the start of the failing step()
        self._held_readings = np.zeros_like(self._readings)
        self._held_sensordata = np.zeros_like(self._sensor_host)
        self._held_time = np.zeros_like(self.time)
        self._none_frozen = np.zeros(self.nworld, bool)
        self._none_frozen.setflags(write=False)
        # whether the host readings are the engine's current values (read() since the last step())
        self._readings_current = False
        self._failure_log = FailureLog(self.name, self.nworld, mujoco_logs=self.logs_failures)
        ensure_log_dir()  # MuJoCo's own log out of the working directory, unless placed already
        self._sensor_config: SensorConfig | None = None
        self._shown_poses = None  # body_poses()' last, per world (batchsim.body_poses)
        self._sensors: SensorSuite | None = None

    @classmethod
    def check_options(cls, options: Mapping[str, Any]) -> None:
        """ValueError, one line, for an option the backend does not take or a value not of its
        type or below its least (batchsim.engine.check_options), at construction."""
        check_options(cls.name, cls.OPTIONS, cls.OPTION_TYPES, cls.OPTION_MINIMA, options)

    @property
    def readings(self) -> np.ndarray:
        """(nworld, ncolumn) float64: all that read() fills, in one block laid out as
        batchsim.readings says. For copying a fleet's readings whole; edit nothing in it."""
        return self._readings

    @property
    def actuator_states(self) -> np.ndarray:
        """(nworld, 3 * n) float64: position, velocity and effort blocks of the n
        `spec.actuator_joints` with an address (mujoco_actuators_states), as the last read()
        left them, without sensor noise. A view where they are columns of their own, else a
        copy (the usual case: a motor's joint reads them as its state interfaces)."""
        return self._noise_free()[0][:, self._actuator_columns]

    def _bind_readings(self, readings: np.ndarray) -> None:
        """Make `readings` (nworld, len(_columns)) the array read() fills; `state`,
        `base_state` and the PIDs' feedback are views of its columns."""
        nstate, nbase = len(self.spec.state), 13 * len(self.spec.floating_bases)
        self._readings = readings
        self.state = readings[:, :nstate]
        self.base_state = readings[:, nstate : nstate + 13] if self.spec.floating_base is not None else None
        self.base_states = readings[:, nstate : nstate + nbase].reshape(len(readings), -1, 13)
        self._feedback = readings[:, readings.shape[1] - self._nfeedback :]

    def _bind_sensordata(self, sensordata: np.ndarray) -> None:
        """Make `sensordata` (nworld, nsensordata) the array read() fills; `self.sensordata`
        holds a view of it per sensor."""
        self._sensor_host = sensordata
        self.sensordata = SensorData(sensordata, self.spec.sensors)

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
        self.sensors  # noqa: B018  (resolved now, so that a bad lidar or noise name fails configure)
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
            self._close_sensors()
            self._close()
            self._opened = False

    # --- read / write ---
    def read(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """Refresh `state`, `base_state`, `sensordata` and `time` from the simulation (INACTIVE
        or ACTIVE). Frozen worlds show what they read before the step() in which they failed."""
        if self._lifecycle not in (S.INACTIVE, S.ACTIVE):
            return ReturnType.OK
        self._refresh()
        self._add_noise()
        return ReturnType.OK

    def write(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """Apply `command` to every world's `ctrl`; a no-op unless ACTIVE.

        A world whose command row holds NaN, inf or a value beyond MAX_COMMAND gets
        BAD_COMMAND and keeps its previous `ctrl`; the other worlds are applied as usual.
        """
        if self._lifecycle is not S.ACTIVE:
            return ReturnType.OK
        command = self._command
        rejected = self._apply_commands() if self._actuation.trivial else None
        if rejected is None:
            ctrl = self._ctrl_host()
            rows = None  # every world's row is good
            # MuJoCo itself zeroes ctrl beyond mjMAXVAL; reject it here, per world, with a status
            # bit. Fast path: two reductions, no temporaries (a NaN makes both comparisons fail).
            if command.size and not (command.min() > -MAX_COMMAND and command.max() < MAX_COMMAND):
                rejected = ~(np.abs(command) < MAX_COMMAND).all(axis=1)
                rows = np.flatnonzero(~rejected)
            if not self._actuation.trivial:
                self._actuate(ctrl, rows)
            elif rows is None:
                ctrl[:, self._ctrl_cols] = command
            else:
                ctrl[np.ix_(rows, self._ctrl_index)] = command[rows]
            self._upload_ctrl()
        if rejected is not None and rejected.any():
            self.status[~rejected] &= ~np.uint8(Status.BAD_COMMAND)
            self.status[rejected] |= np.uint8(Status.BAD_COMMAND)
        elif self.status.any():
            self.status &= ~np.uint8(Status.BAD_COMMAND)
        self._drive_base()  # the BaseVelocityPlugin's target, if any: held from the next step()
        self._apply_wrenches()  # the ExternalWrenchPlugin's xfrc_applied, if any wrench runs
        return ReturnType.OK

    def _apply_commands(self) -> np.ndarray | None:
        """write()'s engine hook for commands that are plain copies into actuators: check each
        world's row of `command` (NaN, inf, beyond MAX_COMMAND), apply the good rows to ctrl on
        the engine (parked worlds keep zero) and return the rejected rows, (nworld,) bool. None:
        the engine has no such path, and write() checks and applies on the host."""
        return None

    def _actuate(self, ctrl: np.ndarray, rows: np.ndarray | None) -> None:
        """write()'s hook for the non-trivial command path (batchsim.actuation): PIDs on motors,
        scaled grippers, mimic joints, interfaces sharing an actuator; rows None: every world."""
        self._actuation.apply(ctrl, self._command, self._feedback, self.time, rows)

    def perform_command_mode_switch(self, start: Sequence[str], stop: Sequence[str] = ()) -> None:
        """Make the `start` command interfaces the ones that drive their actuators, where
        several share one (position and velocity PIDs on one motor), as ros2_control's
        `perform_command_mode_switch`; position is active until told otherwise."""
        self._actuation.switch(start, stop)

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
    def step(self, nstep: int = 1, meanwhile: Callable[[], None] | None = None) -> None:
        """Advance every world `nstep` physics steps; frozen (diverged, overflowed) worlds stay put.

        A world that fails during the call gets DIVERGED or OVERFLOW in `status`, is logged
        once (rate-limited over worlds) and is frozen: it reads as it did before this call
        until `reset` lists it.

        `meanwhile()`, if given, runs once on this thread while the steps run: where they run
        on a device (`steps_on_device`: warp, mjx, a fleet of shards), after they are launched
        and before they are waited for, so host work (the ROS bridge's snapshot) hides under
        the device's; elsewhere just before them. It must not call the system; what read()
        filled and `command` stay as they are until step() returns.
        """
        self._require("step", frozenset({S.INACTIVE, S.ACTIVE}))
        check_nstep(nstep)
        self._failure_log.flush()
        self._meanwhile, self._meanwhile_error = meanwhile, None
        if not self.steps_on_device:
            self._while_stepping()
        try:
            failures = self._step(int(nstep))
            self._while_stepping()  # where the engine's path did not (Warp's CPU device steps on the host)
        except BaseException as e:  # the engine's failure first; meanwhile's, if any, is its context
            if self._meanwhile_error is not None and e.__context__ is None:
                e.__context__ = self._meanwhile_error
            self._meanwhile_error = None
            raise
        finally:
            self._meanwhile = None
        self._readings_current = False
        if failures is not None and failures.worlds.size:
            self._freeze(failures)
        self._raise_meanwhile_error()

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

    def number_worlds_as(self, offset: int, fleet_size: int) -> None:
        """Name world i as `offset + i` of `fleet_size` in failure log lines: for a system that
        is one shard of a larger fleet (batchsim.backends.sharded)."""
        self._failure_log.offset = int(offset)
        self._failure_log.nworld = int(fleet_size)

    def reset(self, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Reset all worlds, or only the listed ones, to the initial state and command (and, with a
        variation that redraws, fresh draws). Clears their status bits, refreshes `state`; no other world changes."""
        self._require("reset", frozenset({S.UNCONFIGURED, S.INACTIVE, S.ACTIVE}))
        if not self._opened:
            raise LifecycleError("cannot reset: the system is UNCONFIGURED; configure it first")
        rows = self._worlds(worlds)
        sel = np.arange(self.nworld) if rows is None else rows
        self.status[sel] = 0  # first: the engine's reset sees them unfrozen
        self._vary(sel)  # their randomized model fields first: the engine's reset sees those too
        self._reset(rows)
        start = self._vary_start(sel)  # start-pose noise: (n, ncommand) commands holding it, or None
        self._command[sel] = self._initial_command if start is None else start
        ctrl = self._ctrl_host()
        ctrl[sel] = self.spec.initial.ctrl
        if self._actuation.trivial:
            ctrl[np.ix_(sel, self._ctrl_index)] = self._command[sel]
        else:
            self._actuation.reset(sel, ctrl, self._command)
        self._upload_ctrl()
        self._place_start(sel)  # the drawn start pose, with the ctrl that holds it in place
        self._reset_base(sel)
        self._reset_wrenches(sel)
        self._refresh()
        self._add_noise()

    # --- the whole joint state (mujoco_ros2_control's reset_world overrides, set_free_joint_state) ---
    def qstate(self, worlds: Sequence[int] | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo's `qpos` `(n, nq)` and `qvel` `(n, nv)` of all or the listed worlds (in the order
        given), float64 arrays of the caller's own: every joint, free joints included."""
        self._require("read the joint state", frozenset({S.INACTIVE, S.ACTIVE}))
        rows = self._worlds(worlds)
        qpos, qvel = self._qstate(np.arange(self.nworld) if rows is None else rows)
        return qpos.astype(np.float64), qvel.astype(np.float64)

    def set_qstate(self, worlds: Sequence[int] | np.ndarray | None, qpos: Any, qvel: Any) -> None:
        """Teleport: write whole `qpos` `(n, nq)` and `qvel` `(n, nv)` rows into all or the listed
        worlds (the order given); `state` shows them at once, the bodies' poses and sensordata
        after the next step (cpu: at once). No other world changes.

        Raises:
          ValueError: a wrong shape, a non-finite value, or a frozen world (reset it first).
        """
        self._require("write the joint state", frozenset({S.INACTIVE, S.ACTIVE}))
        rows = self._worlds(worlds)
        sel = np.arange(self.nworld) if rows is None else rows
        m = self.model
        qpos = np.asarray(qpos, dtype=np.float64)
        qvel = np.asarray(qvel, dtype=np.float64)
        for name, value, width in (("qpos", qpos, m.nq), ("qvel", qvel, m.nv)):
            if value.shape != (len(sel), width):
                raise ValueError(f"{name} must have shape ({len(sel)}, {width}), got {value.shape}")
            if not np.isfinite(value).all():
                raise ValueError(f"{name} holds NaN or infinity")
        frozen = sel[self.frozen[sel]]
        if frozen.size:
            raise ValueError(f"world {frozen[0]} is frozen (it diverged or overflowed): reset it first")
        self._set_qstate(sel, qpos, qvel)
        self._refresh()
        self._add_noise()

    # --- bookkeeping: frozen worlds, world lists, the host arrays ---
    @property
    def frozen(self) -> np.ndarray:
        """(nworld,) bool: the worlds step() leaves alone until they are reset."""
        if not self.status.any():  # the usual case, on every read() and step(): no allocation
            return self._none_frozen
        return (self.status & _FROZEN_BITS) != 0

    def _worlds(self, worlds: Sequence[int] | np.ndarray | None) -> np.ndarray | None:
        """World indices as given, (k,) int64, in the caller's order; None for all
        (batchsim.types.worlds_index: ValueError for a world out of range, a world listed
        twice, a mask of the wrong shape, values that are not integers)."""
        return worlds_index(worlds, self.nworld)

    def _finish_gather(self, readings: np.ndarray | None = None) -> None:
        """Finish readings gathered from the engine (batchsim.readings.Finish: the columns
        read negated, transmissions' joints): `readings` (k, ncolumn), or None: `_readings`
        right after `_read()`. Called once per gather, never on rows already finished."""
        self._finish(self._readings if readings is None else readings)

    def _refresh(self) -> None:
        """The engine's current readings into the host arrays, signed, then frozen worlds' held ones."""
        self._read()
        self._finish_gather()
        self._readings_current = True
        self._show_held()

    def _show_held(self) -> None:
        """Frozen worlds' rows of the host arrays: what they hold (noise-free)."""
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

