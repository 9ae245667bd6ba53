"""The engine hooks: what a backend implements beneath `BatchedSystem` (batchsim.hardware), one
set per engine. The contract calls them and does every check and all the bookkeeping around
them, so that every backend behaves the same; each hook's docstring gives its shapes.

The camera and lidar hooks get their `worlds` ascending and unique (the contract puts the rows
back in the order asked for), as mujoco.batch's ids must be.
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import Future
from typing import Any

import numpy as np

from batchsim.sensors import Camera, Lidar
from batchsim.types import StepFailures


class EngineHooks:
    """The hooks, with their defaults: a backend overrides the engine's (`_open` ... `_park`)
    and those of the cameras and lidars it can render and cast. Mixed into BatchedSystem, whose
    `name`, `nworld` and `_ranges` the defaults use.
    """

    # --- the engine ---
    def _open(self) -> None:
        """Allocate the engine and its buffers (on_configure)."""
        raise NotImplementedError

    def _close(self) -> None:
        """Free the engine (on_cleanup, on_shutdown, on_error)."""

    def _ctrl_host(self) -> np.ndarray:
        """The host (nworld, nu) ctrl array that write() fills: float64, or float32 where the
        engine's ctrl is float32 anyway (warp)."""
        raise NotImplementedError

    def _upload_ctrl(self) -> None:
        """Make the host ctrl the engine's ctrl (a no-op where they are the same memory)."""

    def _read(self) -> None:
        """Every world's current values into `_readings` `(nworld, ncolumn)` (the columns of
        `_columns`), `_sensor_host` `(nworld, nsensordata)` and `time` `(nworld,)`, float64.
        Frozen worlds' rows are overwritten afterwards with what they hold."""
        raise NotImplementedError

    #: whether `_step` calls `_while_stepping()` once its steps are launched on a device, so that
    #: step()'s `meanwhile` runs beside them; False: step() calls it before `_step`
    steps_on_device = False
    _meanwhile: Any = None

    def _step(self, nstep: int) -> StepFailures | None:
        """Advance the unfrozen worlds nstep steps; report the worlds that failed in this call
        (None or an empty StepFailures: none). The base class then freezes them. Where
        `steps_on_device`, call `_while_stepping()` between the launch and the wait."""
        raise NotImplementedError

    def _while_stepping(self) -> None:
        """Run step()'s `meanwhile` now, once (later calls in the same step do nothing). What it
        raises, step() raises once the period is done, so the engine's bookkeeping stays whole."""
        meanwhile, self._meanwhile = self._meanwhile, None
        if meanwhile is not None:
            try:
                meanwhile()
            except Exception as e:
                self._meanwhile_error = e

    _meanwhile_error: Exception | None = None

    def _raise_meanwhile_error(self) -> None:
        """Raise what `meanwhile` raised in this step, if anything (step() calls it once done)."""
        error, self._meanwhile_error = self._meanwhile_error, None
        if error is not None:
            raise error

    def _reset(self, worlds: np.ndarray | None) -> None:
        """Reset the listed worlds (None: all) to `spec.initial`. Their status is already clear."""
        raise NotImplementedError

    def _body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The engine's `xpos` `(n, nbody, 3)` and `xquat` `(n, nbody, 4)` of `worlds` `(n,)`, any
        float dtype, arrays the caller may keep and change; frozen worlds' rows are replaced."""
        raise NotImplementedError(f"the {self.name} backend cannot report body poses")

    def _pose_rows(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Every world's `xpos` `(nworld, nbody, 3)` and `xquat` `(nworld, nbody, 4)` as host
        arrays the engine keeps (any float dtype), current now (read, never changed, by the caller); None
        where there are none (then `_body_poses` gathers). Frozen worlds' rows are replaced
        unless the class says they hold their poses already (`_pose_rows_hold_frozen`)."""
        return None

    def _qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The engine's `qpos` `(n, nq)` and `qvel` `(n, nv)` of `worlds`, any float dtype, copies."""
        raise NotImplementedError(f"the {self.name} backend cannot read the joint state")

    def _set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Write `qpos` `(n, nq)` and `qvel` `(n, nv)` float64 rows into the engine's `worlds` (live ones)."""
        raise NotImplementedError(f"the {self.name} backend cannot write the joint state")

    def _stage_base_velocity(self, target: np.ndarray) -> None:
        """Hold the base's planar velocity (batchsim.base_velocity) in the step() calls from now on:
        `target` `(nworld, 3)` float64, each world's body-frame vx, vy, wz, a NaN row where the
        physics is left alone. Before every physics substep, the free joint's qvel at dofadr +
        HELD_DOFS gets vx, vy rotated into the world by the base's orientation at the start of
        the step() call, and wz. The array is the caller's: copy what is kept."""
        raise NotImplementedError(f"the {self.name} backend cannot hold a base's velocity")

    def _stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        """Set MuJoCo's `xfrc_applied` of `worlds` `(k,)` (ascending, unique) to `xfrc` `(k, nbody,
        6)` float64 (world-frame force, then torque about each body's CoM; batchsim.external_wrench),
        held through the step() calls from now on until staged again; the other worlds' stay as
        they are. The array is the caller's: copy what is kept."""
        raise NotImplementedError(f"the {self.name} backend cannot apply external wrenches")

    def _park(self, worlds: np.ndarray) -> None:
        """Worlds just frozen: for an engine that steps every world whatever happens, keep them
        from costing the others anything (the GPU backends reset them and hold ctrl at zero).
        An engine that skips frozen worlds (cpu) has nothing to do."""

    # --- cameras and lidars ---
    def _render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        """Host (n, H, W, 3) uint8 and (n, H, W) float32 images of `camera` in `worlds`: with `copy`
        arrays of the caller's own (rendered into, not copied: a frame's bytes are written once),
        else possibly buffers the next render overwrites."""
        raise NotImplementedError(f"the {self.name} backend cannot render cameras")

    def _device_frames(self, camera: Camera) -> tuple[Any, Any]:
        """The backend's own (nworld, H, W, 3) uint8 and (nworld, H, W) float32 arrays of `camera`."""
        return self._render_frames(camera, np.arange(self.nworld), False)

    def _prepare_rendering(self, cameras: list[Camera]) -> None:
        """Make ready what `_render_frames_later` needs for `cameras` (nothing by default)."""

    def _render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future:
        """A future of host (n, H, W, 3) uint8 and (n, H, W) float32 images of `camera` in `worlds`
        at the current state, arrays of the caller's own; by default rendered now."""
        future: Future = Future()
        future.set_result(self._render_frames(camera, worlds, True))
        return future

    def _cast_ranges(self, lidar: Lidar, worlds: np.ndarray, copy: bool) -> np.ndarray:
        """(n, nray) float32 REP 117 ranges of `lidar`'s rays in `worlds` at the current state, noise-free;
        with `copy` False it may be a buffer the next cast overwrites."""
        return lidar.ranges(self._cast_rays(lidar, worlds))

    def _cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        """(n, nray) distances along `lidar`'s rays in `worlds` at the current state; < 0: no hit."""
        raise NotImplementedError(f"the {self.name} backend cannot cast lidar rays")

    def _device_ranges(self, lidar: Lidar) -> Any:
        """The backend's own (nworld, nray) float32 REP 117 ranges of every world, noise-free."""
        return self._ranges(lidar, np.arange(self.nworld))

    def _close_sensors(self) -> None:
        """Free renderers and ray-casting buffers (before _close)."""


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
    a value not of the option's type (`types`, else its default's) or below its least (`minima`):
    at construction, where configure would fail on it naming no option (int("four"))."""
    unknown = sorted(set(options) - set(declared))
    if unknown:
        known = ", ".join(declared) or "none"
        raise ValueError(f"unknown option {unknown[0]!r} for backend {backend} (options: {known})")
    for option, value in options.items():
        default = declared[option]
        kind = types.get(option, type(default))
        if kind not in _OPTION_KINDS or (value is None and default is None):
            continue  # object: the backend resolves it (a device), naming what it has
        what, takes = _OPTION_KINDS[kind]
        if not isinstance(value, takes) or (kind is not bool and isinstance(value, bool | np.bool_)):
            raise ValueError(f"option {option} of backend {backend} must be {what}, got {value!r}")
        least = minima.get(option)
        if least is not None and not value >= least:  # NaN too
            raise ValueError(f"option {option} of backend {backend} must be >= {least:g}, got {value!r}")
