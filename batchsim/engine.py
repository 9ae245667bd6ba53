"""The engine: what a backend is beneath the contract (batchsim.hardware.BatchedSystem), one
class per physics library, its names public.

`BatchedSystem(spec, nworld, engine)` owns an `Engine` and calls it; it does every check and all
the bookkeeping around it (lifecycle, command checks, frozen worlds, noise, draws, plugins), so
that every backend behaves the same. An engine only simulates: it steps its worlds, gathers
their values into the host arrays of its `EngineBuffers`, takes their commands from them, and
answers what the contract asks (poses, joint state, images, rays). A new backend is one Engine
subclass plus one registry line (`batchsim.backends.register`); it is done when the contract
suite (tests/test_contract.py) passes on it unchanged.

Capabilities are class attributes (`compiles_first_period`, `sensors_batched`, `device_dtype`,
...); nothing outside batchsim/backends/ asks for a backend by name. Engines never import the
contract: imports point down, the contract onto its engine.

The camera and lidar calls get their `worlds` ascending and unique (the contract puts the rows
back in the order asked for), as mujoco.batch's ids must be.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from typing import Any, ClassVar

import mujoco
import numpy as np

from batchsim.model import RobotSpec, StateColumn
from batchsim.sensors import Camera, Lidar
from batchsim.types import FROZEN, HeldBase, StateSource, StepFailures, as_slice

_FROZEN_BITS = np.uint8(FROZEN)  # converted once: an IntFlag to uint8 costs microseconds a call
#: the state that stepping a world needs, as mj_getState lays it out (Engine.physics_state)
INTEGRATION = int(mujoco.mjtState.mjSTATE_INTEGRATION)


@dataclasses.dataclass
class EngineBuffers:
    """The host arrays an engine reads into and takes its commands from, and their layout.

    The contract makes them (batchsim.hardware); `Engine.bind` may swap them for arrays of the
    same shapes and values in memory of its own (warp: pinned, for DMA), after which the
    contract's views (`state`, `sensordata`, ...) are views of those.

    Attributes:
      readings: (nworld, ncolumn) float64, what `Engine.read` gathers, one column per entry of
        `columns` (batchsim.parts.readings lays them out), raw: the contract finishes them
        (signs, transmissions) after each read.
      sensordata: (nworld, nsensordata) float64, every MJCF sensor's values.
      time: (nworld,) float64, each world's simulation time.
      command: (nworld, ncommand) float64, the command interfaces `write()` applies (an engine
        that checks and applies plain commands itself reads them here: `apply_commands`).
      status: (nworld,) uint8, the contract's Status bits; the engine reads them (`frozen`),
        never writes them.
      columns: (ncolumn,) what each readings column is: its source field and index.
      ctrl_index: (ncommand,) intp, the actuator each command column drives.
    """

    readings: np.ndarray
    sensordata: np.ndarray
    time: np.ndarray
    command: np.ndarray
    status: np.ndarray
    columns: list[StateColumn]
    ctrl_index: np.ndarray

    def __post_init__(self) -> None:
        self._none_frozen = np.zeros(len(self.status), bool)
        self._none_frozen.setflags(write=False)
        # readings columns gathered per source field: (field, readings columns, field indices)
        self._gather: list[tuple[str, Any, Any]] = []
        for source in StateSource:
            cols = [i for i, c in enumerate(self.columns) if c.source is source]
            if cols:
                self._gather.append((source.value, as_slice(cols), as_slice([self.columns[i].index for i in cols])))

    @property
    def nworld(self) -> int:
        return len(self.time)

    @property
    def frozen(self) -> np.ndarray:
        """(nworld,) bool: the worlds the contract holds frozen (diverged, overflowed) until reset."""
        if not self.status.any():  # the usual case, every step: no allocation
            return self._none_frozen
        return (self.status & _FROZEN_BITS) != 0

    def gather(
        self,
        fields: Mapping[str, np.ndarray],
        out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Host engine fields (`READ_FIELDS` `(nworld, ...)` and `time` `(nworld,)`) into readings
        `(nworld, ncolumn)`, sensordata `(nworld, nsensordata)` and time `(nworld,)`: `out`, or
        these buffers."""
        readings, sensordata, time = (self.readings, self.sensordata, self.time) if out is None else out
        for source, cols, idx in self._gather:
            readings[:, cols] = fields[source][:, idx]
        sensordata[:] = fields["sensordata"]
        time[:] = fields["time"]

    def empty_like(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """New readings, sensordata and time arrays shaped as these (a period's start, kept)."""
        return np.empty_like(self.readings), np.empty_like(self.sensordata), np.empty_like(self.time)


class Meanwhile:
    """step()'s `meanwhile`, run once: what it raises is kept and raised once the period is done,
    so the engine's bookkeeping stays whole."""

    def __init__(self, call: Callable[[], None] | None):
        self._call, self.error = call, None

    def __call__(self) -> None:
        call, self._call = self._call, None
        if call is not None:
            try:
                call()
            except Exception as e:
                self.error = e


class Engine:
    """One physics library's worlds, beneath the contract. Subclasses implement `open`, `ctrl`,
    `read`, `step` and `reset`, and override what else they can do; the defaults say what the
    engine cannot.

    Attributes (of an instance):
      spec, nworld, options: as given (options completed with the class's defaults).
      model: `spec.mjmodel`; dt: its timestep.
      buffers: the EngineBuffers bound (`bind`), from construction of the contract on.
    """

    #: the registry name ("cpu", "mjx", "warp")
    name: ClassVar[str] = ""
    #: keyword options the engine takes, with their defaults
    OPTIONS: ClassVar[dict[str, Any]] = {}
    #: the type of each option whose default is None (None also stays allowed): bool, int, float
    #: or str, or object for one the engine resolves itself (a device); others take their default's type
    OPTION_TYPES: ClassVar[dict[str, type]] = {}
    #: the least value of the numeric options that have one
    OPTION_MINIMA: ClassVar[dict[str, float]] = {}
    #: whether one render or scan covers every world at the cost of any subset (one GPU launch)
    sensors_batched: ClassVar[bool] = False
    #: whether the first control period compiles (mjx) or captures (warp) the step's program:
    #: the command line runs one under a progress line before the run starts
    compiles_first_period: ClassVar[bool] = False
    #: whether the engine logs a world's failure itself (C MuJoCo's MUJOCO_LOG.TXT)
    logs_failures: ClassVar[bool] = False
    #: whether MJCF torque sensors read what C MuJoCo's do (MJX's cfrc_int: 0 where C reads a motor's torque)
    reads_torque_sensors: ClassVar[bool] = True
    #: whether `step` runs its steps on a device and calls `meanwhile()` between launch and wait
    steps_on_device: ClassVar[bool] = False
    #: the dtype of the engine's own arrays (`device_arrays`, `device_state`): float64 on the host
    device_dtype: ClassVar[type] = np.float64
    #: whether the engine's device is the host: its device path is the host path
    device_is_host: ClassVar[bool] = True
    #: whether `pose_rows()` already shows frozen worlds' held poses
    pose_rows_hold_frozen: ClassVar[bool] = False
    #: what a world takes (batchsim.startup.PhysicsMemory), a static method
    #: `physics_memory(m, nthread=, nconmax=, njmax=)`; None: not stated (the check is skipped)
    physics_memory: ClassVar[Any] = None

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        if int(nworld) != nworld or nworld < 1:
            raise ValueError(f"nworld must be a positive integer, got {nworld!r}")
        self.check_options(options)
        self.spec = spec
        self.nworld = int(nworld)
        self.options = {**self.OPTIONS, **options}
        self.model: mujoco.MjModel = spec.mjmodel
        self.dt = float(self.model.opt.timestep)

    @classmethod
    def check_options(cls, options: Mapping[str, Any]) -> None:
        """ValueError, one line, for an option the engine does not take or a value not of its
        type or below its least, at construction (where configure would fail naming no option)."""
        check_options(cls.name, cls.OPTIONS, cls.OPTION_TYPES, cls.OPTION_MINIMA, options)

    @classmethod
    def unsupported(cls, spec: RobotSpec) -> str | None:
        """The model feature this engine cannot simulate, or None."""
        return None

    @classmethod
    def variable_fields(cls, m: mujoco.MjModel) -> frozenset[str]:
        """The model fields this engine can give per-world values (`opt.<name>` for options)."""
        return frozenset()

    # --- the host arrays ---
    def bind(self, buffers: EngineBuffers) -> EngineBuffers:
        """Take `buffers` as the arrays `read` fills and commands come from; return those to use:
        these, or arrays of the engine's own memory holding the same values (warp: pinned).
        Called at construction, and again (before `open`) by a fleet's shard that reads into the
        fleet's arrays (batchsim.backends.sharded)."""
        self.buffers = buffers
        return buffers

    # --- lifecycle ---
    def open(self, *, held_base: HeldBase | None = None, varied: tuple[str, ...] = ()) -> None:
        """Allocate the engine and its worlds (on_configure). `held_base`: the free joint whose
        velocity `stage_base_velocity` holds, if the plugin runs; `varied`: the model fields
        drawn per world (`set_model_fields` follows before the first reset)."""
        raise NotImplementedError

    def close(self) -> None:
        """Free the engine (on_cleanup, on_shutdown, on_error)."""

    # --- commands ---
    def ctrl(self) -> np.ndarray:
        """The host (nworld, nu) ctrl array that write() fills: float64, or float32 where the
        engine's ctrl is float32 anyway (warp)."""
        raise NotImplementedError

    def upload_ctrl(self) -> None:
        """Make the host ctrl the engine's ctrl (a no-op where they are the same memory);
        frozen worlds' rows go up as zero where the engine steps them anyway."""

    def apply_commands(self) -> np.ndarray | None:
        """For commands that are plain copies into actuators: check each world's row of
        `buffers.command` (NaN, inf, beyond MAX_COMMAND), apply the good rows to ctrl (frozen
        worlds keep zero) and return the rejected rows, (nworld,) bool. None: no such path here,
        and the contract checks and applies them on the host."""
        return None

    # --- state ---
    def read(self) -> None:
        """Every world's current values into `buffers` (readings raw, sensordata, time)."""
        raise NotImplementedError

    def step(
        self,
        nstep: int,
        meanwhile: Callable[[], None],
        start: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> StepFailures | None:
        """Advance the unfrozen worlds `nstep` steps; report those that failed in this call (None
        or an empty StepFailures: none), read as they were at its start.

        Args:
          meanwhile: call it once, between the launch and the wait where the steps run on a
            device (`steps_on_device`); it raises nothing.
          start: the finished, noise-free readings, sensordata and time of every world as the
            last read() showed them, where they are the engine's current state (no step since):
            an engine may take a failed world's from them (`StepFailures.finished` True). None:
            gather them yourself.
        """
        raise NotImplementedError

    def reset(self, worlds: np.ndarray | None) -> None:
        """Reset the listed worlds (None: all) to `spec.initial`. Their status is already clear."""
        raise NotImplementedError

    def park(self, worlds: np.ndarray) -> None:
        """Worlds just frozen: for an engine that steps every world whatever happens, keep them
        from costing the others anything (reset them, hold ctrl at zero). An engine that skips
        frozen worlds (cpu) has nothing to do."""

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`xpos` `(n, nbody, 3)` and `xquat` `(n, nbody, 4)` of `worlds` `(n,)`, any float dtype,
        arrays the caller may keep and change; frozen worlds' rows are replaced by the caller."""
        raise NotImplementedError(f"the {self.name} backend cannot report body poses")

    def pose_rows(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Every world's `xpos` `(nworld, nbody, 3)` and `xquat` `(nworld, nbody, 4)` as host arrays
        the engine keeps (any float dtype), current now (read, never changed, by the caller);
        None where there are none (then `body_poses` gathers)."""
        return None

    def qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`qpos` `(n, nq)` and `qvel` `(n, nv)` of `worlds`, any float dtype, copies."""
        raise NotImplementedError(f"the {self.name} backend cannot read the joint state")

    def set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Write `qpos` `(n, nq)` and `qvel` `(n, nv)` float64 rows into `worlds` (live ones)."""
        raise NotImplementedError(f"the {self.name} backend cannot write the joint state")

    def physics_state(self, worlds: np.ndarray, what: int = INTEGRATION) -> np.ndarray:
        """The listed worlds' state `(n, mj_stateSize(model, what))` float64, as `mj_getState` lays
        out the `what` (an mjtState mask) of one MjData. Here: the engine's time, qpos, qvel and
        ctrl over a fresh MjData's values (an engine that holds MjData per world gives it whole)."""
        m = self.model
        d = mujoco.MjData(m)
        qpos, qvel = self.qstate(worlds)
        ctrl, time = self.ctrl(), self.buffers.time
        out = np.empty((len(worlds), mujoco.mj_stateSize(m, what)))
        for k, w in enumerate(worlds):
            d.time, d.qpos[:], d.qvel[:], d.ctrl[:] = time[w], qpos[k], qvel[k], ctrl[w]
            mujoco.mj_getState(m, d, out[k], what)
        return out

    def set_physics_state(self, worlds: np.ndarray, states: np.ndarray) -> None:
        """Write whole mjSTATE_INTEGRATION states `(n, nstate)` into `worlds` (a re-run's start)."""
        raise NotImplementedError(f"the {self.name} backend cannot write a whole physics state: re-run on cpu")

    def set_model_fields(self, worlds: np.ndarray, params: dict[str, np.ndarray]) -> None:
        """Make `params[field][worlds]` the engine's values of each field for those worlds.
        `params` holds every world's (field -> (nworld, *shape) float64), the listed rows new;
        an engine may upload whole arrays. Called before the engine resets those worlds."""
        raise NotImplementedError(f"the {self.name} backend cannot vary model fields per world")

    # --- mujoco_ros2_control's plugins (batchsim.plugins) ---
    def stage_base_velocity(self, target: np.ndarray) -> None:
        """Hold the base's planar velocity in the step() calls from now on: `target` `(nworld, 3)`
        float64, each world's body-frame vx, vy, wz, a NaN row where the physics is left alone.
        Before every physics substep, the free joint (`open`'s `held_base`) gets qvel at dofadr +
        HELD_DOFS: vx, vy rotated into the world by the base's orientation at the start of the
        step() call, and wz. The array is the caller's: copy what is kept."""
        raise NotImplementedError(f"the {self.name} backend cannot hold a base's velocity")

    def stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        """Set MuJoCo's `xfrc_applied` of `worlds` `(k,)` (ascending, unique) to `xfrc` `(k, nbody,
        6)` float64, held through the step() calls from now on until staged again; the other
        worlds' stay as they are. The array is the caller's: copy what is kept."""
        raise NotImplementedError(f"the {self.name} backend cannot apply external wrenches")

    # --- cameras and lidars ---
    def render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        """Host (n, H, W, 3) uint8 and (n, H, W) float32 images of `camera` in `worlds`: with `copy`
        arrays of the caller's own, else possibly buffers the next render overwrites."""
        raise NotImplementedError(f"the {self.name} backend cannot render cameras")

    def device_frames(self, camera: Camera) -> tuple[Any, Any]:
        """The engine's own (nworld, H, W, 3) uint8 and (nworld, H, W) float32 arrays of `camera`."""
        return self.render_frames(camera, np.arange(self.nworld), False)

    def prepare_rendering(self, cameras: list[Camera]) -> None:
        """Make ready what `render_frames_later` needs for `cameras` (nothing by default)."""

    def render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future:
        """A future of host (n, H, W, 3) uint8 and (n, H, W) float32 images of `camera` in `worlds`
        at the current state, arrays of the caller's own; by default rendered now."""
        future: Future = Future()
        future.set_result(self.render_frames(camera, worlds, True))
        return future

    def cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        """(n, nray) float32 REP 117 ranges of a ray-casting `lidar` in `worlds` at the current
        state, noise-free; with `copy` False possibly a buffer the next cast overwrites."""
        return lidar.ranges(self.cast_rays(lidar, worlds))

    def cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        """(n, nray) distances along `lidar`'s rays in `worlds` at the current state; < 0: no hit."""
        raise NotImplementedError(f"the {self.name} backend cannot cast lidar rays")

    def device_ranges(self, lidar: Lidar, host: Callable[[], np.ndarray]) -> Any:
        """The engine's own (nworld, nray) float32 REP 117 ranges of every world, noise-free;
        `host()` gives them as a host array (rangefinders read from sensordata, or casts). By
        default that host array, put on the engine's device (`to_device`)."""
        return self.to_device(host())

    def to_device(self, array: np.ndarray) -> Any:
        """A host array as one of the engine's own (a copy on its device; the array itself here)."""
        return array

    def close_sensors(self) -> None:
        """Free renderers and ray-casting buffers (before `close`)."""

    # --- for users who stay on the device ---
    def device_arrays(self) -> dict[str, Any]:
        """The engine's live qpos, qvel, qfrc_actuator, sensordata, ctrl `(nworld, ...)` and time
        `(nworld,)` arrays, zero copy where it can."""
        raise NotImplementedError(f"the {self.name} backend hands out no device arrays")

    def device_state(self, sign: np.ndarray) -> Any:
        """`(nworld, len(sign))` the first state columns gathered now on the device, each times
        its sign, in `device_dtype`. Engines whose device is the host leave this to the contract."""
        raise NotImplementedError(f"the {self.name} backend has no device arrays")

    def write_device(self, command: Any) -> None:
        """ctrl[:, the command's actuators] = `command` on the device, frozen worlds zero."""
        raise NotImplementedError(f"the {self.name} backend has no device arrays")


# an option's type: how a message names it, and the values it takes (NumPy's scalars too; a
# bool is no integer or number here, though Python's bool is an int)
_OPTION_KINDS: dict[type, tuple[str, tuple[type, ...]]] = {
    bool: ("a bool", (bool, np.bool_)),
    int: ("an integer", (int, np.integer)),
    float: ("a number", (int, float, np.integer, np.floating)),
    str: ("a string", (str,)),
}


def check_options(
    backend: str,
    declared: Mapping[str, Any],
    types: Mapping[str, type],
    minima: Mapping[str, float],
    options: Mapping[str, Any],
) -> None:
    """ValueError, one line, for an option `backend` does not take (`declared`: name -> default),
    a value not of the option's type (`types`, else its default's) or below its least (`minima`)."""
    unknown = sorted(set(options) - set(declared))
    if unknown:
        known = ", ".join(declared) or "none"
        raise ValueError(f"unknown option {unknown[0]!r} for backend {backend} (options: {known})")
    for option, value in options.items():
        default = declared[option]
        kind = types.get(option, type(default))
        if kind not in _OPTION_KINDS or (value is None and default is None):
            continue  # object: the engine resolves it (a device), naming what it has
        what, takes = _OPTION_KINDS[kind]
        if not isinstance(value, takes) or (kind is not bool and isinstance(value, bool | np.bool_)):
            raise ValueError(f"option {option} of backend {backend} must be {what}, got {value!r}")
        least = minima.get(option)
        if least is not None and not value >= least:  # NaN too
            raise ValueError(f"option {option} of backend {backend} must be >= {least:g}, got {value!r}")
