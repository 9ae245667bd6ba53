"""What every system shows a user over its parts: the face of the contract that BatchedSystem
(batchsim.hardware, over one engine) and a fleet over several devices (batchsim.backends.sharded,
over its shards) share. Each builds its `parts` and implements what goes to its engine or shards
(read, write, step, reset, the joint state, the draws, the device path); the views of what read()
filled, the commands, cameras, lidars, noise, body poses and the plugins' calls are here, once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from batchsim.lifecycle import LifecycleState, SystemInterface
from batchsim.model import RobotSpec
from batchsim.parts.actuation import Actuation
from batchsim.parts.poses import BodyPoses
from batchsim.parts.readings import Readings
from batchsim.parts.sensing import Sensing
from batchsim.plugins import BaseDrive, BaseVelocity, ExternalWrench, ExternalWrenches, Wrenches
from batchsim.sensors import SensorConfig, SensorSuite
from batchsim.types import FROZEN, Frames, PendingFrames, SensorData, worlds_index

S = LifecycleState
RUNNING = frozenset({S.INACTIVE, S.ACTIVE})
_FROZEN_BITS = np.uint8(FROZEN)  # converted once: an IntFlag to uint8 costs microseconds per read()


@dataclasses.dataclass
class FaceParts:
    """The parts the face reads: a fleet's over devices, and BatchedSystem's (hardware.Parts,
    which adds its draws)."""

    readings: Readings
    actuation: Actuation
    sensing: Sensing
    poses: BodyPoses
    base_drive: BaseDrive
    wrenches: Wrenches


class SystemFace(SystemInterface):
    """`nworld` worlds of `spec`, as a user sees them over `parts` (set by the subclass, with
    `_command`, the (nworld, ncommand) array write() takes).

    Attributes:
      spec, nworld, model, dt: the model and how many worlds.
      status: (nworld,) uint8 bitmask of Status, current after step() and write().
      reason: why this backend was chosen, for `batchsim info` and the status line.
    """

    parts: FaceParts
    _command: np.ndarray

    def __init__(self, spec: RobotSpec, nworld: int):
        super().__init__()
        if int(nworld) != nworld or nworld < 1:
            raise ValueError(f"nworld must be a positive integer, got {nworld!r}")
        self.spec, self.nworld = spec, int(nworld)
        self.model: mujoco.MjModel = spec.mjmodel
        self.dt = float(self.model.opt.timestep)
        self.reason = ""
        self.status = np.zeros(self.nworld, np.uint8)
        self._none_frozen = np.zeros(self.nworld, bool)
        self._none_frozen.setflags(write=False)

    # --- what read() shows ---
    @property
    def state(self) -> np.ndarray:
        return self.parts.readings.state

    @property
    def base_state(self) -> np.ndarray | None:
        return self.parts.readings.base_state

    @property
    def base_states(self) -> np.ndarray:
        return self.parts.readings.base_states

    @property
    def sensordata(self) -> SensorData:
        return self.parts.readings.sensordata

    @property
    def time(self) -> np.ndarray:
        return self.parts.readings.time

    @property
    def readings(self) -> np.ndarray:
        """(nworld, ncolumn) float64: all that read() fills, in one block laid out as
        batchsim.parts.readings says. For copying a fleet's readings whole; edit nothing in it."""
        return self.parts.readings.array

    @property
    def actuator_states(self) -> np.ndarray:
        """(nworld, 3 * n) float64: position, velocity and effort blocks of the n
        `spec.actuator_joints` with an address (mujoco_actuators_states), as the last read()
        left them, without sensor noise."""
        return self.parts.sensing.noise_free()[0][:, self.parts.readings.actuator_columns]

    @property
    def frozen(self) -> np.ndarray:
        """(nworld,) bool: the worlds step() leaves alone until they are reset."""
        if not self.status.any():  # the usual case, on every read() and step(): no allocation
            return self._none_frozen
        return (self.status & _FROZEN_BITS) != 0

    # --- interfaces ---
    def export_state_interfaces(self) -> list[str]:
        """State interface names, `"<joint>/<interface>"` and `"<sensor>/<field>"`, in column order."""
        return self.spec.state_interfaces

    def export_command_interfaces(self) -> list[str]:
        """Command interface names, `"<joint>/<interface>"`, in column order."""
        return self.spec.command_interfaces

    @property
    def ctrl_index(self) -> np.ndarray:
        """(ncommand,) intp: the actuator (the column of MuJoCo's ctrl, and of `device_arrays()["ctrl"]`)
        each command interface drives."""
        return np.array([c.actuator_id for c in self.spec.commands], dtype=np.intp)

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
        set_command_rows(self.spec, self._command, command, worlds_index(worlds, self.nworld))

    # --- cameras, lidars, noise (batchsim.parts.sensing) ---
    @property
    def sensors(self) -> SensorSuite:
        """The cameras, lidars and sensor noise of every world, and which worlds want each."""
        return self.parts.sensing.suite

    def set_sensor_config(self, config: SensorConfig | str | Path | Mapping[str, Any]) -> None:
        """Configure cameras, lidars, noise and mujoco_ros2_control's plugins (batchsim.sensors.config:
        a SensorConfig, YAML file or mapping), before configure(). Raises SensorConfigError naming
        the file and key at fault, ConfigurationError for a plugin this system cannot run."""
        self._require("set the sensor configuration", frozenset({S.UNKNOWN, S.UNCONFIGURED}))
        config = self.parts.sensing.configure(config)
        self.parts.base_drive.configure(config.base_velocity)
        self.parts.wrenches.configure(config.external_wrench)

    @property
    def true_state(self) -> np.ndarray:
        """(nworld, nstate) float64: `state` without sensor noise; `state` itself when there is none."""
        return self.parts.sensing.true_state

    @property
    def true_sensordata(self) -> SensorData:
        """Every MJCF sensor by name without noise, (nworld, dim); `sensordata` when there is none."""
        return self.parts.sensing.true_sensordata

    def render(
        self, camera: str, worlds: Sequence[int] | np.ndarray | None = None, *, device: bool = False, copy: bool = True
    ) -> Frames:
        """Render `camera` in all or the listed worlds (indices or a bool mask), at the current state.

        Returns Frames(rgb (n, H, W, 3) uint8, depth (n, H, W) float32), row i for world
        `worlds[i]` in the order given (a bool mask lists worlds in order): top row first, depth
        in metres along the optical axis, +inf where nothing was hit, NaN where noise dropped a
        pixel. `device=True` returns the engine's own arrays for every world without a host
        copy or noise (Warp arrays on warp, JAX on mjx, NumPy on cpu); `copy=False` may return
        buffers the next render overwrites.
        """
        self._require("render", RUNNING)
        if device:
            if worlds is not None:
                raise ValueError("render(device=True) renders every world: leave worlds=None and index on the device")
            return self.parts.sensing.render_device(camera)
        return self.parts.sensing.render(camera, self._listed(worlds), copy)

    def render_async(self, camera: str, worlds: Sequence[int] | np.ndarray | None = None) -> PendingFrames:
        """Start rendering `camera` in all or the listed worlds at the current state; return at once.

        `result()` of the PendingFrames gives what `render(camera, worlds)` would have given
        now (host arrays of the caller's own, noise included), waiting if need be. cpu and mjx
        draw them on a background thread with its own OpenGL context, from a copy of the
        worlds' poses taken now, so the caller can step on meanwhile (SensorSampler does:
        the physics and the rendering then use two cores); the others render before
        returning. Renders run in the order they were asked for.
        """
        self._require("render", RUNNING)
        return self.parts.sensing.render_async(camera, self._listed(worlds))

    def prepare_rendering(self) -> None:
        """Set up now what the first `render_async` would otherwise set up inside the loop: on cpu
        and mjx the render thread and its OpenGL context (making one holds Python's GIL for
        ~0.2 s, a stalled control period if the loop runs). Nothing on warp, whose render
        context, holding every world's frames, is made on a camera's first render.
        SensorSampler calls it when it is made."""
        self._require("prepare rendering", RUNNING)
        self.parts.sensing.prepare_rendering()

    def scan(
        self, lidar: str, worlds: Sequence[int] | np.ndarray | None = None, *, device: bool = False, copy: bool = True
    ) -> np.ndarray:
        """One scan of `lidar` in all or the listed worlds: (n, nray) float32 ranges in metres, REP 117
        (+inf: no hit within range_max, -inf: closer than range_min, NaN: dropped by noise), row i
        for world `worlds[i]` in the order given (a bool mask lists worlds in order).

        Rangefinder lidars read the MJCF rangefinders (as of the last step, like every
        sensor); the others cast their rays now, at the current state. `device=True` returns
        the engine's own (nworld, nray) array of every world without a host copy or noise
        (a Warp array on warp, JAX on mjx, NumPy on cpu), as `render(device=True)`;
        `copy=False` may return a buffer the next scan of this lidar overwrites.
        """
        self._require("scan", RUNNING)
        if device:
            if worlds is not None:
                raise ValueError("scan(device=True) scans every world: leave worlds=None and index on the device")
            return self.parts.sensing.scan_device(lidar)
        return self.parts.sensing.scan(lidar, self._listed(worlds), copy)

    def _listed(self, worlds: Sequence[int] | np.ndarray | None) -> np.ndarray:
        rows = worlds_index(worlds, self.nworld)
        return np.arange(self.nworld) if rows is None else rows

    # --- body poses (batchsim.parts.poses) ---
    def body_poses(self, worlds: Sequence[int] | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every body's pose in the world frame, in all or the listed worlds (indices, in the order
        given, or a bool mask): positions `(n, nbody, 3)` and orientation quaternions
        `(n, nbody, 4)` (w, x, y, z), float64 arrays of the caller's own; body 0 is the world body.

        They are MuJoCo's `xpos`/`xquat` as the engine computed them in its last step, i.e. the
        kinematics of the state before the last physics substep, like `sensordata`; after
        reset(), of the reset state. A frozen world shows the poses the last call gave it before
        it froze (the initial state's, if no call did). Nothing is fetched or computed until
        the first call (batchsim.model.frames turns them into tf transforms).
        """
        self._require("read body poses", RUNNING)
        return self.parts.poses.body_poses(worlds_index(worlds, self.nworld))

    def body_poses_into(
        self, xpos_out: np.ndarray, xquat_out: np.ndarray, bodies: Sequence[int] | np.ndarray | slice = slice(None)
    ) -> None:
        """Every world's poses of `bodies` (default all) into `xpos_out` `(nworld, nb, 3)` and
        `xquat_out` `(nworld, nb, 4)` (views will do: tf's channel holds both side by side), as
        body_poses() gives them: what tf copies each control period."""
        self._require("read body poses", RUNNING)
        self.parts.poses.body_poses_into(xpos_out, xquat_out, bodies)

    # --- mujoco_ros2_control's plugins (batchsim.plugins) ---
    @property
    def base_velocity(self) -> BaseVelocity | None:
        """The BaseVelocityPlugin's per-world commands, or None when the sensor configuration has no such plugin."""
        return self.parts.base_drive.velocity

    def set_base_velocity(self, command: Any, worlds: Sequence[int] | np.ndarray | None = None) -> None:
        """Command the base's planar velocity in all or the listed worlds, as a cmd_vel message
        does: `command` `(n, 3)` or `(3,)`, body-frame vx, vy [m/s] and wz [rad/s] (a Twist's
        linear.x, linear.y, angular.z). Each world's is stamped with its sim time (`time`, as
        read() last showed it): it holds for the plugin's cmd_timeout of sim time, then the base
        is held still. Takes effect at the next write().

        Raises:
          ValueError: no BaseVelocityPlugin configured, a wrong shape, a value not finite or
            beyond MAX_COMMAND, a world out of range or listed twice.
        """
        sel = self._listed(worlds)
        self.parts.base_drive.command(sel, command, self.time[sel])

    @property
    def external_wrenches(self) -> ExternalWrenches | None:
        """The running wrenches (batchsim.plugins.external_wrench), or None before the first apply_wrench()."""
        return self.parts.wrenches.store

    def apply_wrench(
        self, wrenches: ExternalWrench | Sequence[ExternalWrench], worlds: Sequence[int] | np.ndarray | None = None
    ) -> int:
        """Apply wrenches in all or the listed worlds from the next write() on, as one
        apply_wrench request does in each: every vector in its body's frame, rotated with the
        body at each write(), the force acting at `point`; each lasts its `duration` of sim time
        from `time` as read() last showed it. Checked whole before anything is applied.

        Returns the request's number, for `wrench_running`.

        Raises:
          ValueError: a body not in the model (upstream's words: "Body 'x' not found in MuJoCo
            model."), a wrong shape, a value not finite or beyond MAX_COMMAND, a frozen world, a
            world out of range or listed twice.
        """
        self._require("apply external wrenches", RUNNING)
        sel = self._listed(worlds)
        return self.parts.wrenches.apply(wrenches, sel, self.time[sel], self.frozen[sel])

    def wrench_running(self, requests: Any) -> np.ndarray:
        """Whether each request (apply_wrench()'s numbers, any shape) still has a wrench running
        in some world: bool, the shape of `requests`."""
        return self.parts.wrenches.running(requests)

    def _checked_qstate(self, worlds: Sequence[int] | np.ndarray | None, qpos: Any, qvel: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """set_qstate()'s checks (its docstring says which), the worlds listed as indices."""
        return check_qstate(self.model, worlds_index(worlds, self.nworld), self.frozen, qpos, qvel)


def set_command_rows(spec: RobotSpec, into: np.ndarray, command: Any, rows: np.ndarray | None) -> None:
    """`command` `(n, ncommand)` or `(ncommand,)` into rows `rows` of `into` (None: every row):
    set_command()'s copy and its shape check, naming the interfaces."""
    command = np.asarray(command, dtype=np.float64)
    n = len(into) if rows is None else len(rows)
    ncommand = len(spec.commands)
    if command.shape not in ((ncommand,), (n, ncommand)):
        raise ValueError(
            f"command must have shape ({n}, {ncommand}) or ({ncommand},), got {command.shape}"
            + (f"; command interfaces: {', '.join(spec.command_interfaces)}" if ncommand else "")
        )
    into[slice(None) if rows is None else rows] = command


def check_qstate(m: Any, rows: np.ndarray | None, frozen: np.ndarray, qpos: Any, qvel: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """set_qstate()'s checks: the worlds (None: all), `qpos` `(n, nq)` and `qvel` `(n, nv)` as
    float64; ValueError for a wrong shape, a non-finite value, or a frozen world."""
    sel = np.arange(len(frozen)) if rows is None else rows
    qpos = np.asarray(qpos, dtype=np.float64)
    qvel = np.asarray(qvel, dtype=np.float64)
    for name, value, width in (("qpos", qpos, m.nq), ("qvel", qvel, m.nv)):
        if value.shape != (len(sel), width):
            raise ValueError(f"{name} must have shape ({len(sel)}, {width}), got {value.shape}")
        if not np.isfinite(value).all():
            raise ValueError(f"{name} holds NaN or infinity")
    stuck = sel[frozen[sel]]
    if stuck.size:
        raise ValueError(f"world {stuck[0]} is frozen (it diverged or overflowed): reset it first")
    return sel, qpos, qvel
