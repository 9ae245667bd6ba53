"""mujoco_ros2_control's ExternalWrenchPlugin, in every world: forces and torques on named bodies
for a while.

Upstream (mujoco_ros2_control_plugins/src/external_wrench_plugin.cpp) takes wrenches through its
`apply_wrench` service and, at every control update (the hardware interface's write()), zeroes
`xfrc_applied` and adds every running wrench into it, which its simulation then applies at each
physics step until the next update:

    F_world   = R (s F_body)                   R: the body's xmat (body -> world)
    tau_world = R (s tau_body)                 s: the ramp-down scale
    p_world   = xpos + R point_body
    xfrc_applied[body] += (F_world, tau_world + (p_world - xipos) x F_world)

A wrench that came at sim time t0 ends at `end = t0 + duration`; with a ramp_down > 0 it is
scaled by s = max(0, (end - now) / ramp_down) once fewer than ramp_down seconds are left; it is
dropped after the update at which now >= end, so a zero duration acts for one control update
(one physics step where the control rate is the physics rate). Several wrenches add.

Here, for `nworld` worlds at once:

- `ExternalWrenchConfig`: the plugin's params, read from its YAML (batchsim.plugins.config).
  force_arrow_scale and torque_arrow_scale size upstream's `~/wrench_markers` arrows, which
  batchsim does not publish; the instance name names the service (`service`).
- `ExternalWrench`: one wrench of a request, its vectors `(3,)` or one row per listed world.
- `ExternalWrenches`: the running wrenches of every world, one row each, and the xfrc_applied
  rows of an update, computed for all of them at once (`xfrc`).
- `Wrenches`, the system's part: `apply_wrench()`, `wrench_running()`,
  `external_wrenches`. write() computes the xfrc_applied rows of every world with a wrench (and
  zero rows for those whose last one ended) on the host, from `body_poses()` (the kinematics of
  the state before the last physics substep, as upstream's snapshot of mjData), and stages them
  (`Engine.stage_xfrc`); the engine holds them through the step() calls that follow.
  reset() drops the listed worlds' wrenches; a world that freezes drops its own at the next write().

The ROS side: ros_bridge/worker/wrench.py serves `<ns>/<plugin name>/apply_wrench`, and
ros_bridge/simulation.py answers once the request's wrenches have run (sim time).
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import mujoco
import numpy as np

from batchsim.types import MAX_COMMAND, check_plugin_runs

PLUGIN_TYPE = "mujoco_ros2_control_plugins/ExternalWrenchPlugin"
SERVICE = "apply_wrench"  # relative, on the plugin's sub-node: <ns>/<plugin name>/apply_wrench
_KEYS = ("force_arrow_scale", "torque_arrow_scale")
_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclasses.dataclass(frozen=True)
class ExternalWrenchConfig:
    """The plugin's parameters, with upstream's defaults (external_wrench_plugin.hpp).

    Attributes:
      name: the plugin's instance name (its key under `mujoco_plugins`): rclcpp's sub-node
        namespace, so the service is `<ns>/<name>/apply_wrench` (`service`).
      force_arrow_scale, torque_arrow_scale: m/N and m/(N m), the markers' arrow lengths (not
        published by batchsim: read and checked only).
      where: the file and key path it came from, for messages.
    """

    name: str = "external_wrench"
    force_arrow_scale: float = 0.01
    torque_arrow_scale: float = 0.1
    where: str = "<external wrench plugin>"

    @property
    def service(self) -> str:
        """The service's name under each world's namespace (rclcpp resolves the relative
        `apply_wrench` of a sub-node to `<node's namespace>/<sub-namespace>/apply_wrench`)."""
        return f"{self.name}/{SERVICE}"

    @classmethod
    def parse(cls, name: str, params: Mapping[str, Any], where: str) -> ExternalWrenchConfig:
        """The plugin's params (without `type`) as its YAML gives them; ValueError: one line
        naming `where` and the key at fault."""
        if not _TOKEN.match(name):
            raise ValueError(
                f"{where}: {name!r} cannot name the plugin's sub-node (letters, digits and '_', not "
                "starting with a digit): its service is <ns>/<name>/apply_wrench"
            )
        unknown = sorted(set(params) - set(_KEYS), key=str)
        if unknown:
            raise ValueError(f"{where}: unknown key {unknown[0]!r} (known: type, {', '.join(_KEYS)})")
        scales = {}
        for key in _KEYS:
            value = params.get(key, getattr(cls, key))
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"{where}.{key}: must be a finite number, got {value!r}")
            scales[key] = float(value)
        return cls(name, where=where, **scales)


@dataclasses.dataclass(frozen=True)
class ExternalWrench:
    """One wrench of a request (mujoco_ros2_control_msgs/ExternalWrench).

    Attributes:
      body: the MJCF body (the message's wrench.header.frame_id).
      force: N, in the body's frame: `(3,)`, or `(n, 3)`, a row per world the request lists.
      torque: N m, in the body's frame, likewise.
      point: m, where the force acts, in the body's frame (relative to its origin), likewise.
      duration: s of sim time, `()` or `(n,)`; 0: one control update.
      ramp_down: s, `()` or `(n,)`: the last stretch of the duration over which the wrench falls
        linearly to zero; 0: none.
    """

    body: str
    force: Any = (0.0, 0.0, 0.0)
    torque: Any = (0.0, 0.0, 0.0)
    point: Any = (0.0, 0.0, 0.0)
    duration: Any = 0.0
    ramp_down: Any = 0.0


def _rotations(quat: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotation matrices of unit quaternions `(k, 4)` (w, x, y, z), as mju_quat2Mat."""
    w, x, y, z = (quat[:, i] for i in range(4))
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )


class ExternalWrenches:
    """The running wrenches of `nworld` worlds, one row each (k rows).

    Attributes:
      world, body: (k,) int64.
      force, torque, point: (k, 3) float64, in the body's frame.
      end: (k,) float64, the sim time at which each ends.
      ramp_down: (k,) float64, s.
      request: (k,) int64, the apply_wrench() call each came with.
    """

    _FIELDS = ("world", "body", "force", "torque", "point", "end", "ramp_down", "request")

    def __init__(self) -> None:
        self.world = np.zeros(0, np.int64)
        self.body = np.zeros(0, np.int64)
        self.force = np.zeros((0, 3))
        self.torque = np.zeros((0, 3))
        self.point = np.zeros((0, 3))
        self.end = np.zeros(0)
        self.ramp_down = np.zeros(0)
        self.request = np.zeros(0, np.int64)

    @property
    def count(self) -> int:
        return len(self.world)

    def add(self, **rows: np.ndarray) -> None:
        """Append rows, one array per field."""
        for name in self._FIELDS:
            setattr(self, name, np.concatenate([getattr(self, name), rows[name]]))

    def keep(self, rows: np.ndarray) -> None:
        """Keep the masked rows `(k,)` only."""
        for name in self._FIELDS:
            setattr(self, name, getattr(self, name)[rows])

    def xfrc(self, time: np.ndarray, xquat: np.ndarray, ipos: np.ndarray, out: np.ndarray, at: np.ndarray) -> None:
        """Add every row's xfrc_applied contribution at the worlds' sim `time` `(nworld,)` into
        `out[at[i], body[i]]` (`out` (m, nbody, 6), `at` (k,)): upstream's update, from each row's
        body orientation `xquat` `(k, 4)` (w, x, y, z) and CoM offset `ipos` `(k, 3)` (body_ipos),
        the ramp-down scale taken at `time`. The body's position cancels out of the transport:
        p_world - xipos = R (point - ipos)."""
        left = self.end - time[self.world]
        scale = np.ones(self.count)
        ramping = (self.ramp_down > 0) & (left < self.ramp_down)
        scale[ramping] = np.maximum(0.0, left[ramping] / self.ramp_down[ramping])
        rot = _rotations(xquat)
        force = np.einsum("kij,kj->ki", rot, self.force * scale[:, None])
        torque = np.einsum("kij,kj->ki", rot, self.torque * scale[:, None])
        arm = np.einsum("kij,kj->ki", rot, self.point - ipos)
        np.add.at(out, (at, self.body), np.concatenate([force, torque + np.cross(arm, force)], axis=1))

    def expire(self, time: np.ndarray) -> None:
        """Drop the rows that have run out at the worlds' sim `time` `(nworld,)` (now >= end)."""
        self.keep(time[self.world] < self.end)


def _rows(value: Any, width: int | None, n: int, what: str) -> np.ndarray:
    """`value` as (n, width) (or (n,) for width None) float64: one row for every world, or one each."""
    array = np.asarray(value, dtype=np.float64)
    shape = () if width is None else (width,)
    if array.shape not in (shape, (n, *shape)):
        raise ValueError(f"{what} must have shape {shape} or {(n, *shape)}, got {array.shape}")
    return np.broadcast_to(array, (n, *shape))


class Wrenches:
    """The plugin's part of the system (batchsim.hardware): `store` (the running wrenches, None
    before the first), what apply_wrench() records, and what write() and reset() stage on the
    engine (`stage(worlds, xfrc)`: Engine.stage_xfrc). `poses(worlds)` gives the listed worlds'
    body orientations (the system's body_poses). `runs`: whether the system can apply them (a
    fleet over several devices cannot)."""

    def __init__(
        self,
        model: mujoco.MjModel,
        nworld: int,
        stage: Callable[[np.ndarray, np.ndarray], None],
        poses: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
        *,
        runs: bool = True,
    ):
        self._model, self._nworld, self._stage, self._poses, self.runs = model, nworld, stage, poses, runs
        self.store: ExternalWrenches | None = None
        self._wrenched = np.zeros(nworld, bool)  # worlds whose engine xfrc_applied is not zero
        self._requests = 0  # apply_wrench() calls so far
        self.configured = False  # whether the plugin is configured (configure)

    def configure(self, config: ExternalWrenchConfig | None) -> None:
        """The plugin's params from the sensor configuration (None: not configured)."""
        check_plugin_runs(config, self.runs, "ExternalWrenchPlugin")
        self.configured = config is not None

    def apply(self, wrenches: ExternalWrench | Sequence[ExternalWrench], sel: np.ndarray, time: np.ndarray, frozen: np.ndarray) -> int:
        """apply_wrench() in worlds `sel` `(n,)` at their sim `time` `(n,)`; `frozen` `(n,)` bool.
        Checked whole before anything is applied; the request's number."""
        if not self.runs:
            raise ValueError("external wrenches are not applied on a fleet spread over several devices: use one")
        n, m = len(sel), self._model
        wrenches = [wrenches] if isinstance(wrenches, ExternalWrench) else list(wrenches)
        parts: dict[str, list[np.ndarray]] = {name: [] for name in ExternalWrenches._FIELDS}
        for i, w in enumerate(wrenches):
            body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, w.body)
            if body < 0:
                raise ValueError(f"Body '{w.body}' not found in MuJoCo model.")
            values = {
                "force": _rows(w.force, 3, n, f"wrench {i} ('{w.body}'): force"),
                "torque": _rows(w.torque, 3, n, f"wrench {i} ('{w.body}'): torque"),
                "point": _rows(w.point, 3, n, f"wrench {i} ('{w.body}'): point"),
                "duration": _rows(w.duration, None, n, f"wrench {i} ('{w.body}'): duration"),
                "ramp_down": _rows(w.ramp_down, None, n, f"wrench {i} ('{w.body}'): ramp_down"),
            }
            for what, value in values.items():
                if not (np.abs(value) < MAX_COMMAND).all():  # NaN fails the comparison too
                    limit = f"finite and below {MAX_COMMAND:g} in magnitude"
                    raise ValueError(f"Wrench {i} ('{w.body}'): {what} must be {limit}.")
            for name in ("force", "torque", "point", "ramp_down"):
                parts[name].append(values[name])
            parts["world"].append(sel)
            parts["body"].append(np.full(n, body, np.int64))
            parts["end"].append(time + values["duration"])
        if frozen.any():
            raise ValueError(f"world {sel[frozen][0]} is frozen (it diverged or overflowed): reset it first")
        self._requests += 1
        if wrenches:
            if self.store is None:
                self.store = ExternalWrenches()
            rows_of = {name: np.concatenate(arrays) for name, arrays in parts.items() if name != "request"}
            count = len(rows_of["world"])
            self.store.add(**rows_of, request=np.full(count, self._requests, np.int64))
        return self._requests

    def running(self, requests: Any) -> np.ndarray:
        """Whether each request (apply()'s numbers, any shape) still has a wrench running in some
        world: bool, the shape of `requests`."""
        running = np.zeros(0, np.int64) if self.store is None else self.store.request
        return np.isin(np.asarray(requests, np.int64), running)

    def stage(self, time: np.ndarray, frozen: np.ndarray) -> None:
        """write()'s part: the xfrc_applied rows of the wrenched worlds at their sim `time` to the
        engine, then the wrenches that ran out dropped (upstream's update)."""
        store = self.store
        if store is None:
            return
        if store.count and frozen.any():
            store.keep(~frozen[store.world])  # a frozen world's wrenches end with it
        active = np.unique(store.world)
        rows = np.union1d(active, np.flatnonzero(self._wrenched))
        if not rows.size:
            return
        xfrc = np.zeros((rows.size, self._model.nbody, 6))
        if active.size:
            xquat = self._poses(active)[1][np.searchsorted(active, store.world), store.body]
            ipos = self._model.body_ipos[store.body]
            store.xfrc(time, xquat, ipos, xfrc, np.searchsorted(rows, store.world))
            store.expire(time)
        self._stage(rows, xfrc)
        self._wrenched[:] = False
        self._wrenched[active] = True

    def reset(self, worlds: np.ndarray) -> None:
        """reset()'s part: the worlds' wrenches dropped, their xfrc_applied zero."""
        store = self.store
        if store is None:
            return
        store.keep(~np.isin(store.world, worlds))
        rows = worlds[self._wrenched[worlds]]
        if rows.size:
            self._stage(np.sort(rows), np.zeros((rows.size, self._model.nbody, 6)))
            self._wrenched[rows] = False
