"""A policy's observation, built for every world at once from named terms, as Isaac Lab's and
mjlab's observation managers build theirs: each term a function of the simulation's state, then
scaled, clipped and stacked with its history (oldest first), the terms concatenated in order.

Term names follow mjlab's observation groups (what an mjlab ONNX export's `observation_names`
lists) and Isaac Lab's mdp functions:

    joint_pos, joint_pos_rel        the policy's joints' positions minus the default pose
    joint_pos_abs                   their positions
    joint_vel, joint_vel_rel        their velocities (the default velocity is zero)
    base_lin_vel                    the floating base's linear velocity, in the base frame
    base_ang_vel                    its angular velocity, in the base frame
    projected_gravity               gravity's direction (unit) in the base frame
    actions, last_action            the policy's last raw action
    command, generated_commands,    the world's command (a joint target, a velocity: the
      velocity_commands               controller's command input)
    sensor:<name>                   an MJCF sensor's reading

A term may instead name its function (`func:` in the YAML), as an Isaac Lab ObsTerm does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

#: term name -> the function it is, by mjlab's and Isaac Lab's names
ALIASES = {
    "joint_pos": "joint_pos_rel",
    "joint_vel": "joint_vel_rel",
    "actions": "last_action",
    "command": "generated_commands",
    "velocity_commands": "generated_commands",
}


@dataclasses.dataclass(frozen=True)
class Term:
    """One observation term: `name` as the policy lists it, `func` what computes it, its `width`
    per world, `scale` (a number or one per entry), `clip` (low, high) or None, and `history`
    (how many steps are stacked, oldest first)."""

    name: str
    func: str
    width: int
    scale: np.ndarray
    clip: tuple[float, float] | None = None
    history: int = 1
    sensor: str = ""

    @property
    def size(self) -> int:
        return self.width * self.history


@dataclasses.dataclass
class Context:
    """What the terms read besides the simulation: the policy's joints as state columns, the
    default pose, the last action and each world's command."""

    pos_cols: np.ndarray  # (njoint,) state columns of the joints' positions, policy order
    vel_cols: np.ndarray  # (njoint,) of their velocities
    default: np.ndarray  # (njoint,) the default pose
    last_action: np.ndarray  # (nworld, naction)
    command: np.ndarray  # (nworld, ncommand)


def _base(sim: Any) -> np.ndarray:
    base = sim.base_state
    if base is None:
        raise ValueError("the model has no floating base")
    return base


def rotate_into_base(base: np.ndarray, v: np.ndarray) -> np.ndarray:
    """`v` (n, 3) in the world frame into each base's frame: R(q)^T v, q = (w, x, y, z)."""
    w, x, y, z = (base[:, 3 + k : 4 + k] for k in range(4))
    u = np.concatenate([x, y, z], axis=1)
    # R^T v = v + 2 w' (u' x v) + 2 u' x (u' x v) with the conjugate (w, -u)
    t = 2.0 * np.cross(-u, v)
    return v + w * t + np.cross(-u, t)


def _gravity(sim: Any, ctx: Context) -> np.ndarray:
    base = _base(sim)
    down = np.zeros((len(base), 3))
    down[:, 2] = -1.0
    return rotate_into_base(base, down)


FUNCTIONS: dict[str, Callable[[Any, Context], np.ndarray]] = {
    "joint_pos_rel": lambda sim, ctx: sim.state[:, ctx.pos_cols] - ctx.default,
    "joint_pos_abs": lambda sim, ctx: sim.state[:, ctx.pos_cols],
    "joint_vel_rel": lambda sim, ctx: sim.state[:, ctx.vel_cols],
    "base_lin_vel": lambda sim, ctx: rotate_into_base(_base(sim), _base(sim)[:, 7:10]),
    "base_ang_vel": lambda sim, ctx: _base(sim)[:, 10:13],
    "projected_gravity": _gravity,
    "last_action": lambda sim, ctx: ctx.last_action,
    "generated_commands": lambda sim, ctx: ctx.command,
}
FUNCTIONS["joint_pos"] = FUNCTIONS["joint_pos_abs"]  # as a `func:`, Isaac Lab's joint_pos is absolute
FUNCTIONS["joint_vel"] = FUNCTIONS["joint_vel_rel"]


def function_of(name: str, func: str | None) -> str:
    """The function a term of `name` is (`func` where given, else by the names above)."""
    if func is not None:
        return func
    if name.startswith("sensor:"):
        return "sensor"
    return ALIASES.get(name, name)


def width_of(func: str, njoint: int, naction: int, ncommand: int, sensor_dim: int = 0) -> int:
    """Values per world of a term's function."""
    if func in ("joint_pos_rel", "joint_pos_abs", "joint_pos", "joint_vel_rel", "joint_vel"):
        return njoint
    if func in ("base_lin_vel", "base_ang_vel", "projected_gravity"):
        return 3
    if func == "last_action":
        return naction
    if func == "generated_commands":
        return ncommand
    if func == "sensor":
        return sensor_dim
    raise KeyError(func)


KNOWN = sorted({*FUNCTIONS, *ALIASES, "sensor:<name>"})


class Observations:
    """The observation of `nworld` worlds: `terms` in order, each with its history ring."""

    def __init__(self, terms: Sequence[Term], nworld: int):
        self.terms = list(terms)
        self.size = sum(t.size for t in self.terms)
        self._history = [np.zeros((nworld, t.history, t.width), np.float32) for t in self.terms]
        self._filled = np.zeros(nworld, bool)  # a world's history holds real steps (else: filled at the next)

    def __call__(self, sim: Any, ctx: Context) -> np.ndarray:
        """(nworld, size) float32: every world's observation now, each term's history shifted."""
        parts = []
        fresh = ~self._filled
        for term, ring in zip(self.terms, self._history, strict=True):
            if term.func == "sensor":
                value = sim.sensordata[term.sensor]
            else:
                value = FUNCTIONS[term.func](sim, ctx)
            value = np.asarray(value, dtype=np.float64) * term.scale
            if term.clip is not None:
                value = np.clip(value, *term.clip)
            if term.history > 1:
                ring[:, :-1] = ring[:, 1:]
                ring[:, -1] = value
                if (
                    fresh.any()
                ):  # a world's first step: its history is this step, repeated (Isaac Lab's reset)
                    ring[fresh] = value[fresh, None, :]
                parts.append(ring.reshape(len(ring), -1))
            else:
                parts.append(value.astype(np.float32))
        self._filled[:] = True
        return np.concatenate(parts, axis=1).astype(np.float32, copy=False)

    def reset(self, worlds: np.ndarray) -> None:
        """The listed worlds start over: their histories refill at their next step."""
        self._filled[worlds] = False
