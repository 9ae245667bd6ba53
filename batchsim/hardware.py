"""The contract: a batched mirror of ros2_control's `hardware_interface::SystemInterface`.

`BatchedSystem(spec, nworld, engine)` is the one concrete system: `nworld` copies of one robot
(or of one fleet's world of several, batchsim.fleet) on one engine (batchsim.engine: cpu, mjx,
warp, or one registered). It does every check and all the bookkeeping, so every engine behaves
the same, and owns named parts (`parts`), each built with what it needs:

- `readings` (batchsim.parts.readings): the host arrays read() fills, their views (`state`,
  `base_state`, `sensordata`, `time`) and the frozen rule;
- `actuation` (batchsim.parts.actuation): commands -> ctrl beyond a copy (PIDs, scaling, mimics);
- `sensing` (batchsim.parts.sensing): cameras, lidars, sensor noise;
- `poses` (batchsim.parts.poses): every body's pose, tf's source;
- `draws` (batchsim.variation.worlds): each world's randomized model fields and start pose;
- `base_drive`, `wrenches` (batchsim.plugins): mujoco_ros2_control's two plugins.

What a user sees (batchsim.contract.Contract lists it whole):

- `export_state_interfaces()` / `export_command_interfaces()`: ros2_control names.
- `state` `(nworld, nstate)` float64, refreshed by `read(time, period)`.
- `command` `(nworld, ncommand)` float64, applied by `write(time, period)` into `ctrl`;
  `write` does nothing unless ACTIVE.
- `step(nstep)`, `reset(worlds=None)`, `status` `(nworld,)` bitmask of `Status`,
  `sensordata[name]` `(nworld, dim)`, `time` `(nworld,)` float64 on every backend.
- `render`, `scan`, `sensors`, `true_state`, `true_sensordata`; `body_poses`, `body_poses_into`;
  `set_base_velocity`, `apply_wrench`; `set_variation`, `world_params`; `qstate`, `set_qstate`;
  `device_arrays`, `device_state`, `write_device` for users who stay on the engine's device.

A world that fails (diverges, or overflows a buffer that cannot grow) is frozen, by one rule on
every backend: until `reset` lists it, it reads the noise-free values `read()` would have shown
just before the `step()` call in which it failed, with no fresh sensor noise, and the failure is
logged once, naming the world and why (batchsim.parts.failures).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from batchsim.backends import varying_backends
from batchsim.engine import Engine, EngineBuffers, Meanwhile
from batchsim.lifecycle import CallbackReturn, LifecycleError, LifecycleState
from batchsim.model import RobotSpec, initial_command
from batchsim.parts.actuation import Actuation
from batchsim.parts.face import RUNNING, FaceParts, SystemFace
from batchsim.parts.failures import FailureLog, ensure_log_dir
from batchsim.parts.poses import BodyPoses
from batchsim.parts.readings import Readings
from batchsim.parts.resimulation import Resimulation
from batchsim.parts.sensing import Sensing
from batchsim.plugins import BaseDrive, Wrenches
from batchsim.types import (
    MAX_COMMAND,
    ConfigurationError,
    ReturnType,
    Status,
    StepFailures,
    as_slice,
    check_nstep,
    worlds_index,
)
from batchsim.variation import Bound, Variation
from batchsim.variation.worlds import WorldDraws

S = LifecycleState


@dataclasses.dataclass
class Parts(FaceParts):
    """What a BatchedSystem is made of beside its engine, each part built with what it needs:
    the face's parts and each world's draws."""

    draws: WorldDraws


class BatchedSystem(SystemFace, Resimulation):
    """`nworld` copies of one robot on `engine`, behind ros2_control's SystemInterface.

    Attributes (valid from on_configure on):
      nworld: number of worlds.
      engine: the Engine it owns; parts: its Parts.
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
      name, options, and the engine's capabilities (`compiles_first_period`, `sensors_batched`,
        `reads_torque_sensors`, `logs_failures`, `steps_on_device`, `device_dtype`), copied.
    """

    def __init__(self, spec: RobotSpec, nworld: int, engine: Engine):
        super().__init__(spec, nworld)
        if engine.nworld != nworld or engine.spec is not spec:
            raise ValueError(f"the engine was made for {engine.nworld} worlds of {engine.spec.name}, not {nworld} of {spec.name}")
        self.engine = engine
        self.name, self.options = engine.name, engine.options
        for capability in ("compiles_first_period", "sensors_batched", "reads_torque_sensors", "logs_failures",
                           "steps_on_device", "device_dtype"):  # fmt: skip
            setattr(self, capability, getattr(engine, capability))
        actuation = Actuation(spec, self.nworld)
        readings = Readings(spec, self.nworld, actuation.feedback_columns)
        self._initial_command = initial_command(spec)
        self._ctrl_index = np.array([c.actuator_id for c in spec.commands], dtype=np.intp)
        self._ctrl_cols = as_slice(self._ctrl_index)  # a slice where it can be: faster
        command = np.tile(self._initial_command, (self.nworld, 1)).reshape(self.nworld, len(spec.commands))
        self._bind(readings, engine.bind(self._buffers(readings, command)))
        frozen = lambda: self.frozen  # noqa: E731  (the parts ask the system, whose status changes)
        self.parts = Parts(
            readings=readings,
            actuation=actuation,
            sensing=Sensing(spec, self.nworld, readings, engine, frozen),
            poses=BodyPoses(spec, self.nworld, engine, frozen, hold_frozen=engine.pose_rows_hold_frozen),
            draws=WorldDraws(
                spec, self.nworld, engine.name, engine.variable_fields(self.model), lambda f: varying_backends(f, self.model)
            ),
            base_drive=BaseDrive(self.model, self.nworld, engine.stage_base_velocity),
            wrenches=Wrenches(self.model, self.nworld, engine.stage_xfrc, lambda worlds: self.body_poses(worlds)),
        )
        self._opened = False
        self._failure_log = FailureLog(self.name, self.nworld, mujoco_logs=self.logs_failures)
        ensure_log_dir()  # MuJoCo's own log out of the working directory, unless placed already

    def _buffers(self, readings: Readings, command: np.ndarray) -> EngineBuffers:
        r = readings
        return EngineBuffers(r.array, r.sensor_array, r.time, command, self.status, r.columns, self._ctrl_index)

    def _bind(self, readings: Readings, buffers: EngineBuffers) -> None:
        """Make `buffers` (the engine's answer to `bind`) the arrays read() fills and write() takes."""
        self._engine_buffers = buffers
        readings.bind(buffers.readings, buffers.sensordata, buffers.time)
        self._command = buffers.command

    def share_host_arrays(self, readings: np.ndarray, sensordata: np.ndarray, command: np.ndarray) -> None:
        """Make `readings` (nworld, ncolumn), `sensordata` (nworld, nsensordata) and `command`
        (nworld, ncommand), C-contiguous float64, the arrays read() fills and write() takes its
        commands from, in place of this system's own (`command` gets its current rows): a fleet's
        shard (batchsim.backends.sharded) then reads into the fleet's arrays and copies nothing.
        Before configure(); the caller keeps the arrays alive."""
        self._require("share its host arrays", frozenset({S.UNKNOWN, S.UNCONFIGURED}))
        r = self.parts.readings
        mine = {"readings": r.array, "sensordata": r.sensor_array, "command": self._command}
        for name, array in zip(mine, (readings, sensordata, command), strict=True):
            like = mine[name]
            if array.shape != like.shape or array.dtype != np.float64 or not array.flags.c_contiguous:
                raise ValueError(f"{name} must be C-contiguous float64 {like.shape}, got {array.dtype} {array.shape}")
        command[:] = self._command
        buffers = dataclasses.replace(self._engine_buffers, readings=readings, sensordata=sensordata, command=command)
        self._bind(r, self.engine.bind(buffers))

    # --- lifecycle ---
    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        if self.spec.problems:
            raise ConfigurationError(f"{self.spec.name}: " + "; ".join(self.spec.problems))
        self.sensors  # noqa: B018  (resolved now, so that a bad lidar or noise name fails configure)
        if not self._opened:
            bound = self.parts.draws.bound
            self.engine.open(held_base=self.parts.base_drive.held_base, varied=tuple(bound.fields) if bound else ())
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
            self.engine.close_sensors()
            self.engine.close()
            self._opened = False

    # --- read / write ---
    def read(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """Refresh `state`, `base_state`, `sensordata` and `time` from the simulation (INACTIVE
        or ACTIVE). Frozen worlds show what they read before the step() in which they failed."""
        if self._lifecycle not in RUNNING:
            return ReturnType.OK
        self._refresh()
        self.parts.sensing.add_noise()
        return ReturnType.OK

    def write(self, time: float | None = None, period: float | None = None) -> ReturnType:
        """Apply `command` to every world's `ctrl`; a no-op unless ACTIVE.

        A world whose command row holds NaN, inf or a value beyond MAX_COMMAND gets
        BAD_COMMAND and keeps its previous `ctrl`; the other worlds are applied as usual.
        """
        if self._lifecycle is not S.ACTIVE:
            return ReturnType.OK
        command, actuation = self._command, self.parts.actuation
        rejected = self.engine.apply_commands() if actuation.trivial else None
        if rejected is None:
            ctrl = self.engine.ctrl()
            rows = None  # every world's row is good
            # MuJoCo itself zeroes ctrl beyond mjMAXVAL; reject it here, per world, with a status
            # bit. Fast path: two reductions, no temporaries (a NaN makes both comparisons fail).
            if command.size and not (command.min() > -MAX_COMMAND and command.max() < MAX_COMMAND):
                rejected = ~(np.abs(command) < MAX_COMMAND).all(axis=1)
                rows = np.flatnonzero(~rejected)
            if not actuation.trivial:
                actuation.apply(ctrl, command, self.parts.readings.feedback, self.time, rows)
            elif rows is None:
                ctrl[:, self._ctrl_cols] = command
            else:
                ctrl[np.ix_(rows, self._ctrl_index)] = command[rows]
            self.engine.upload_ctrl()
        if rejected is not None and rejected.any():
            self.status[~rejected] &= ~np.uint8(Status.BAD_COMMAND)
            self.status[rejected] |= np.uint8(Status.BAD_COMMAND)
        elif self.status.any():
            self.status &= ~np.uint8(Status.BAD_COMMAND)
        drive, wrenches = self.parts.base_drive, self.parts.wrenches
        if drive.velocity is not None or wrenches.store is not None:  # the plugins' staging, where one runs
            frozen = self.frozen
            drive.drive(self.time, frozen)  # the BaseVelocityPlugin's target
            wrenches.stage(self.time, frozen)  # the ExternalWrenchPlugin's xfrc_applied
        return ReturnType.OK

    def perform_command_mode_switch(self, start: Sequence[str], stop: Sequence[str] = ()) -> None:
        """Make the `start` command interfaces the ones that drive their actuators, where
        several share one (position and velocity PIDs on one motor), as ros2_control's
        `perform_command_mode_switch`; position is active until told otherwise."""
        self.parts.actuation.switch(start, stop)

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
        self._require("step", RUNNING)
        check_nstep(nstep)
        self._failure_log.flush()
        once = Meanwhile(meanwhile)
        if not self.steps_on_device:
            once()
        readings = self.parts.readings
        start = (*self.parts.sensing.noise_free(), self.time) if readings.current else None
        try:
            failures = self.engine.step(int(nstep), once, start)
            once()  # where the engine's path did not (Warp's CPU device steps on the host)
        except BaseException as e:  # the engine's failure first; meanwhile's, if any, is its context
            if once.error is not None and e.__context__ is None:
                e.__context__ = once.error
            raise
        readings.current = False
        if failures is not None and failures.worlds.size:
            self._freeze(failures)
        if once.error is not None:
            raise once.error

    def _freeze(self, failures: StepFailures) -> None:
        """Hold what the failed worlds read before the failing step, mark them, park them, say so."""
        worlds = failures.worlds
        self.parts.readings.hold(failures)
        self.status[worlds] |= failures.status.astype(np.uint8)
        self.engine.park(worlds)
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
        rows = worlds_index(worlds, self.nworld)
        sel = np.arange(self.nworld) if rows is None else rows
        engine, parts = self.engine, self.parts
        self.status[sel] = 0  # first: the engine's reset sees them unfrozen
        parts.draws.draw(sel, engine.set_model_fields)  # their model fields first: the engine's reset sees them
        engine.reset(rows)
        start = parts.draws.draw_start(sel)  # start-pose noise: (n, ncommand) commands holding it, or None
        self._command[sel] = self._initial_command if start is None else start
        ctrl = engine.ctrl()
        ctrl[sel] = self.spec.initial.ctrl
        if parts.actuation.trivial:
            ctrl[np.ix_(sel, self._ctrl_index)] = self._command[sel]
        else:
            parts.actuation.reset(sel, ctrl, self._command)
        engine.upload_ctrl()
        parts.draws.place_start(sel, engine.set_qstate)  # the drawn start pose, with the ctrl that holds it
        parts.base_drive.reset(sel)
        parts.wrenches.reset(sel)
        self._refresh()
        parts.sensing.add_noise()

    def _refresh(self) -> None:
        """The engine's current readings into the host arrays, finished, then frozen worlds' held ones."""
        readings = self.parts.readings
        self.engine.read()
        readings.finish(readings.array)
        readings.current = True
        if self.status.any():
            readings.show_held(self.frozen)

    # --- the whole joint state (mujoco_ros2_control's reset_world overrides, set_free_joint_state) ---
    def qstate(self, worlds: Sequence[int] | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo's `qpos` `(n, nq)` and `qvel` `(n, nv)` of all or the listed worlds (in the order
        given), float64 arrays of the caller's own: every joint, free joints included."""
        self._require("read the joint state", RUNNING)
        rows = worlds_index(worlds, self.nworld)
        qpos, qvel = self.engine.qstate(np.arange(self.nworld) if rows is None else rows)
        return qpos.astype(np.float64), qvel.astype(np.float64)

    def set_qstate(self, worlds: Sequence[int] | np.ndarray | None, qpos: Any, qvel: Any) -> None:
        """Teleport: write whole `qpos` `(n, nq)` and `qvel` `(n, nv)` rows into all or the listed
        worlds (the order given); `state` shows them at once, the bodies' poses and sensordata
        after the next step (cpu: at once). No other world changes.

        Raises:
          ValueError: a wrong shape, a non-finite value, or a frozen world (reset it first).
        """
        self._require("write the joint state", RUNNING)
        sel, qpos, qvel = self._checked_qstate(worlds, qpos, qvel)
        self.engine.set_qstate(sel, qpos, qvel)
        self._refresh()
        self.parts.sensing.add_noise()

    # --- per-world randomization (batchsim.variation.worlds) ---
    def set_variation(self, variation: Variation | str | Path | Mapping[str, Any] | None, first_world: int = 0) -> None:
        """Vary the model per world from configure on: a Variation, a YAML file or its mapping
        (batchsim.variation.spec); None: every world the same.

        Args:
          first_world: the number of this system's world 0 in the fleet (`--world-offset`, or a
            shard's first world): world i draws as world `first_world + i` of any fleet does.

        Raises:
          VariationError: the file, or a name in it, does not fit the model (one line, file and key).
          ConfigurationError: a field this backend cannot vary per world, naming those that can.
          LifecycleError: the system is configured already.
        """
        if self._opened or self.lifecycle_state is not S.UNCONFIGURED:
            raise LifecycleError("set the variation before configure(): the worlds draw when they are allocated")
        self.parts.draws.set(variation, first_world)

    @property
    def variation(self) -> Variation | None:
        """The Variation the worlds draw from, or None."""
        bound = self.parts.draws.bound
        return None if bound is None else bound.variation

    @property
    def variation_bound(self) -> Bound | None:
        """The variation as resolved against this model (what a draw writes, and how), or None."""
        return self.parts.draws.bound

    def world_params(self, worlds: Sequence[int] | np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Each world's current values of every varied field: field -> `(n, *shape)` float64 copies,
        for all or the listed worlds; `start_qpos` `(n, nq)` too where start-pose noise is drawn.
        Empty without a variation. Valid from configure on."""
        if self.parts.draws.bound is not None and not self._opened:
            raise LifecycleError("world_params(): the worlds draw at configure(); configure first")
        return self.parts.draws.world_params(worlds_index(worlds, self.nworld))

    def reseed(self, seed: int) -> None:
        """Draw from `seed` from now on, as a new run would: every world's next reset is its
        first draw again (a gymnasium `reset(seed=...)`). Nothing changes until a reset."""
        self.parts.draws.reseed(seed)

    def draw_numbers(self) -> np.ndarray:
        """(nworld,) int64: how many times each world has drawn since its first (0 at start)."""
        return self.parts.draws.draw_numbers()

    # --- for users who stay on the engine's device ---
    def device_arrays(self) -> dict[str, Any]:
        """The engine's live qpos, qvel, qfrc_actuator, sensordata, ctrl `(nworld, ...)` and time
        `(nworld,)` arrays, zero copy (the engine's docstring says how long each stays valid):
        Warp arrays on warp, JAX arrays on mjx, the batch's float64 NumPy arrays on cpu."""
        return self.engine.device_arrays()

    @property
    def data(self) -> Any:
        """mjx: the simulation's own `mjx.Data`, batched over worlds (the engine's `data`); a Data
        of the same structure assigned replaces the simulation's state."""
        return self.engine.data  # type: ignore[attr-defined]

    @data.setter
    def data(self, value: Any) -> None:
        self.engine.data = value  # type: ignore[attr-defined]

    def device_state(self) -> Any:
        """`(nworld, nstate)` the state interfaces, gathered now on the engine's device, signed as
        `state` is (`export_state_interfaces()` order), without sensor noise; rows of frozen
        worlds are parked and meaningless until reset. warp reuses one buffer: the next call
        overwrites it.

        Raises:
          ConfigurationError: interfaces that pass through transmissions (computed on the host).
        """
        self._require("read the device state", RUNNING)
        if self.spec.transmissions:
            raise ConfigurationError(
                "device_state(): the transmissions' joint interfaces are computed on the host: use read() and state"
            )
        if self.engine.device_is_host:  # the engine's device is the host: the state, gathered and signed now
            self._refresh()
            return self.parts.readings.state
        return self.engine.device_state(np.array([c.sign for c in self.spec.state], np.float32))

    def write_device(self, command: Any) -> None:
        """Apply `command` `(nworld, ncommand)` (any DLPack array, float32 or float64, on the
        engine's device) to every world's ctrl on the device, as write() applies `self.command`;
        parked (frozen) worlds keep a zero ctrl. No BAD_COMMAND check (the values never reach
        the host): a NaN reaches MuJoCo, which diverges that world, frozen as always. ACTIVE only.

        Raises:
          ConfigurationError: commands that do not map one to one onto actuators (PIDs, scaled
            grippers, mimic joints, transmissions: they run on the host; use command and write()).
        """
        self._require("write commands on the device", frozenset({S.ACTIVE}))
        if not self.parts.actuation.trivial:
            raise ConfigurationError(
                "write_device(): these command interfaces are not plain copies into actuators "
                "(PIDs, scaling, mimic joints or transmissions run on the host): use command and write()"
            )
        shape = tuple(getattr(command, "shape", ()))
        want = (self.nworld, len(self.spec.commands))
        if shape != want:
            raise ValueError(f"command must have shape {want}, got {shape}")
        if self.engine.device_is_host:
            self._command[:] = np.asarray(command)
            self.write()
            return
        self.engine.write_device(command)

    def __getattr__(self, name: str) -> Any:
        """What the engine states beyond the contract, read through the system: warp's `nconmax`
        and `njmax`, a device engine's `device`, cpu's `nthread`."""
        if name.startswith("_") or name in ("engine", "parts"):
            raise AttributeError(name)
        try:
            return getattr(self.__dict__["engine"], name)
        except (KeyError, AttributeError):
            raise AttributeError(f"{type(self).__name__} on {self.__dict__.get('name', '?')} has no attribute {name!r}") from None

