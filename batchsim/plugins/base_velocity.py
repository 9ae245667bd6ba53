"""mujoco_ros2_control's BaseVelocityPlugin, in every world: a free base held at a commanded
planar velocity.

Upstream (mujoco_ros2_control_plugins/src/base_velocity_plugin.cpp) subscribes to a cmd_vel
topic and, at every control update, stages a hard kinematic override of the base body's free
joint, which its simulation writes into `qvel` before every physics step: `qvel[0:2]` the
commanded body-frame (vx, vy) rotated into the world by the body's orientation, `qvel[5]` the
yaw rate wz. Contacts and bodies mounted on the base (a swinging arm) cannot change those
three DOFs; height, roll and pitch stay the physics'. The planar speed is clamped to
max_linear_velocity (its direction kept), wz to max_yaw_rate, and a command older than
cmd_timeout, or none yet, is zero velocity: the base is held still rather than left to coast.

Here, for `nworld` worlds at once:

- `BaseVelocityConfig`: the plugin's parameters, read from its YAML (batchsim.plugins.config).
- `BaseVelocity`: per world, the last command `(nworld, 3)` (body-frame vx, vy [m/s], wz
  [rad/s]) and the sim time it came; `target(time)` is what to hold: clamped, zero where stale.
- `BaseDrive`, the system's part: `base_velocity`, `set_base_velocity()`. write()
  stages the target (`Engine.stage_base_velocity`) and the engine holds it before
  every physics substep of the step() calls that follow, as upstream's simulation re-applies
  its staged override before every mj_step, the rotation taken from the base's orientation at
  the start of each step() call (upstream: at its control update, which the loop runs right
  before stepping; it reads `xmat`, one substep older than `qpos`). Rows of NaN, a frozen
  world's or a reset one's until the next write(), leave the physics alone, as upstream's NaN
  staging does. reset() drops the listed worlds' commands.

The ROS side (ros_bridge/plan.py) subscribes every world's `<ns>/<cmd_vel_topic>`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping
from typing import Any

import mujoco
import numpy as np

from batchsim.types import MAX_COMMAND, ConfigurationError, HeldBase, check_plugin_runs

PLUGIN_TYPE = "mujoco_ros2_control_plugins/BaseVelocityPlugin"
#: the free joint's qvel entries the override writes, from its first: world vx, vy; body wz
HELD_DOFS = (0, 1, 5)
_KEYS = ("body", "cmd_vel_topic", "use_stamped_twist", "max_linear_velocity", "max_yaw_rate", "cmd_timeout")
_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_TOPIC = re.compile(rf"^/?{_TOKEN}(/{_TOKEN})*$")


@dataclasses.dataclass(frozen=True)
class BaseVelocityConfig:
    """The plugin's parameters, with upstream's defaults (base_velocity_plugin.hpp).

    Attributes:
      body: the MJCF body of the base; it must have a free joint.
      cmd_vel_topic: under each world's namespace, relative or absolute alike (`/cmd_vel` of
        world 3 is `/world_3/cmd_vel`; at the root namespace exactly `/cmd_vel`).
      use_stamped_twist: geometry_msgs/TwistStamped instead of Twist (the stamp is not used).
      max_linear_velocity: m/s, the planar speed's limit; inf: none.
      max_yaw_rate: rad/s; inf: none.
      cmd_timeout: s of sim time after which a command is zero velocity.
      name: the plugin's instance name (its key under `mujoco_plugins`).
      where: the file and key path it came from, for messages.
    """

    body: str
    cmd_vel_topic: str = "cmd_vel"
    use_stamped_twist: bool = False
    max_linear_velocity: float = math.inf
    max_yaw_rate: float = math.inf
    cmd_timeout: float = 0.5
    name: str = "base_velocity_plugin"
    where: str = "<base velocity plugin>"

    @classmethod
    def parse(cls, name: str, params: Mapping[str, Any], where: str) -> BaseVelocityConfig:
        """The plugin's params (without `type`) as its YAML gives them; ValueError: one line
        naming `where` and the key at fault."""
        unknown = sorted(set(params) - set(_KEYS), key=str)
        if unknown:
            raise ValueError(f"{where}: unknown key {unknown[0]!r} (known: type, {', '.join(_KEYS)})")
        body = params.get("body")
        if not isinstance(body, str) or not body:
            raise ValueError(f"{where}.body: required: the MJCF body of the base (it needs a free joint)")
        topic = params.get("cmd_vel_topic", "cmd_vel")
        if not isinstance(topic, str) or not _TOPIC.match(topic):
            raise ValueError(
                f"{where}.cmd_vel_topic: {topic!r} is not a topic name (letters, digits and '_' "
                "between '/'; it goes under each world's namespace)"
            )
        stamped = params.get("use_stamped_twist", False)
        if not isinstance(stamped, bool):
            raise ValueError(f"{where}.use_stamped_twist: must be true or false, got {stamped!r}")
        limits = {}
        for key in ("max_linear_velocity", "max_yaw_rate", "cmd_timeout"):
            value = params.get(key, getattr(cls, key))
            if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
                raise ValueError(f"{where}.{key}: must be a number >= 0 (.inf for none), got {value!r}")
            limits[key] = float(value)
        return cls(body, topic, stamped, name=str(name), where=where, **limits)


def command_problem(command: np.ndarray) -> str | None:
    """What is wrong with base velocity commands `(n, 3)`, or None: every value must be finite
    and below MAX_COMMAND (a huge velocity would make the world diverge)."""
    bad = ~(np.abs(command) < MAX_COMMAND)  # NaN fails the comparison too
    if not bad.any():
        return None
    value = command[np.nonzero(bad)][0]
    return f"vx, vy and wz must be finite and below {MAX_COMMAND:g} in magnitude, got {value}"


def world_velocity(quat: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(n, 3) qvel values of the held DOFs: `target`'s body-frame (vx, vy) `(n, 3)` rotated into
    the world by `quat` `(n, 4)` (w, x, y, z, any norm, as the free joint's qpos holds it), and
    wz as is. The mjx and warp backends inline the same arithmetic."""
    w, x, y, z = (quat[:, k] for k in range(4))
    s = 2.0 / (w * w + x * x + y * y + z * z)
    vx, vy, wz = target[:, 0], target[:, 1], target[:, 2]
    out = np.empty_like(target)
    out[:, 0] = (1.0 - s * (y * y + z * z)) * vx + s * (x * y - w * z) * vy
    out[:, 1] = s * (x * y + w * z) * vx + (1.0 - s * (x * x + z * z)) * vy
    out[:, 2] = wz
    return out


class BaseVelocity:
    """The plugin in `nworld` worlds: each world's last command and when it came.

    Attributes:
      config: its parameters.
      body_id: the base body.
      qposadr, dofadr: its free joint's first qpos (position, then quaternion w, x, y, z) and
        first qvel entry.
      command: (nworld, 3) float64, body-frame vx, vy [m/s] and wz [rad/s] as last commanded.
      stamp: (nworld,) float64, the sim time each world's command came; -inf: none.
    """

    def __init__(self, config: BaseVelocityConfig, model: mujoco.MjModel, nworld: int):
        self.config = config
        self.body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, config.body)
        if self.body_id < 0:
            bodies = [model.body(i).name for i in range(1, model.nbody)]
            raise ConfigurationError(
                f"{config.where}.body: no body {config.body!r} in the model (bodies: {', '.join(bodies) or 'none'})"
            )
        free = [
            j for j in range(model.njnt)
            if model.jnt_bodyid[j] == self.body_id and model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE
        ]  # fmt: skip
        if not free:
            raise ConfigurationError(
                f"{config.where}.body: body {config.body!r} has no free joint: the plugin holds a free joint's velocity"
            )
        self.qposadr = int(model.jnt_qposadr[free[0]])
        self.dofadr = int(model.jnt_dofadr[free[0]])
        self.command = np.zeros((nworld, 3))
        self.stamp = np.full(nworld, -np.inf)

    def set(self, worlds: np.ndarray, command: np.ndarray, time: np.ndarray) -> None:
        """Commands `(k, 3)` for `worlds` `(k,)`, which came at sim times `time` `(k,)`."""
        self.command[worlds] = command
        self.stamp[worlds] = time

    def clear(self, worlds: np.ndarray) -> None:
        """Forget the listed worlds' commands (they were reset)."""
        self.command[worlds] = 0.0
        self.stamp[worlds] = -np.inf

    def target(self, time: np.ndarray) -> np.ndarray:
        """(nworld, 3) float64 of the caller's own: the body-frame velocity to hold at the worlds'
        sim `time` `(nworld,)`: the command, zero where older than cmd_timeout (or none), its
        planar speed scaled down to max_linear_velocity and wz clipped to max_yaw_rate."""
        c = self.config
        fresh = time - self.stamp <= c.cmd_timeout
        target = np.where(fresh[:, None], self.command, 0.0)
        speed = np.hypot(target[:, 0], target[:, 1])
        fast = speed > c.max_linear_velocity
        if fast.any():
            target[fast, :2] *= (c.max_linear_velocity / speed[fast])[:, None]
        np.clip(target[:, 2], -c.max_yaw_rate, c.max_yaw_rate, out=target[:, 2])
        return target


class BaseDrive:
    """The plugin's part of the system (batchsim.hardware): `velocity` (None without the plugin),
    what set_base_velocity() records, and what write() and reset() stage on the engine
    (`stage(target)`: Engine.stage_base_velocity). `runs`: whether the system can run it (a fleet
    over several devices cannot)."""

    def __init__(self, model: mujoco.MjModel, nworld: int, stage: Callable[[np.ndarray], None], *, runs: bool = True):
        self._model, self._nworld, self._stage, self._runs = model, nworld, stage, runs
        self.velocity: BaseVelocity | None = None
        self._staged: np.ndarray | None = None  # (nworld, 3): the target the engine holds now

    def configure(self, config: BaseVelocityConfig | None) -> None:
        """The plugin's params from the sensor configuration (None: no plugin)."""
        check_plugin_runs(config, self._runs, "BaseVelocityPlugin")
        self._staged = None
        self.velocity = None if config is None else BaseVelocity(config, self._model, self._nworld)

    @property
    def held_base(self) -> HeldBase | None:
        """The free joint the engine holds (Engine.open's `held_base`), or None."""
        v = self.velocity
        return None if v is None else HeldBase(v.qposadr, v.dofadr)

    @property
    def staged(self) -> np.ndarray | None:
        """(nworld, 3): the target the engine holds now (NaN rows: none), None before the first write()."""
        return self._staged

    def command(self, sel: np.ndarray, command: Any, time: np.ndarray) -> None:
        """set_base_velocity() for worlds `sel` `(n,)` at their sim `time` `(n,)`: `command` `(n, 3)`
        or `(3,)`, body-frame vx, vy [m/s] and wz [rad/s]. ValueError: no plugin, a wrong shape,
        a value not finite or beyond MAX_COMMAND."""
        drive = self.velocity
        if drive is None:
            raise ValueError("no BaseVelocityPlugin: give its mujoco_plugins YAML as the sensors configuration")
        command = np.asarray(command, dtype=np.float64)
        if command.shape not in ((3,), (len(sel), 3)):
            n = len(sel)
            raise ValueError(f"command must have shape ({n}, 3) or (3,): vx, vy, wz; got {command.shape}")
        command = np.broadcast_to(command, (len(sel), 3))
        problem = command_problem(command)
        if problem is not None:
            raise ValueError(problem)
        drive.set(sel, command, time)

    def drive(self, time: np.ndarray, frozen: np.ndarray) -> None:
        """write()'s part: the target of every world at its sim `time` (NaN for frozen ones) staged."""
        drive = self.velocity
        if drive is None:
            return
        target = drive.target(time)
        if frozen.any():
            target[frozen] = np.nan
        self._staged = target
        self._stage(target)

    def reset(self, worlds: np.ndarray) -> None:
        """reset()'s part: the worlds' commands dropped and their override lifted until the next write()."""
        drive = self.velocity
        if drive is None:
            return
        drive.clear(worlds)
        if self._staged is not None:
            self._staged[worlds] = np.nan
            self._stage(self._staged)
