"""Each world's draws, a part of the system: the variation bound to the model, every world's
current values, and what a reset draws.

A Variation (batchsim.variation.spec) is given before configure; each world draws at its first
reset (configure's) and, with `redraw_on_reset`, again at each reset that lists it, its n-th draw
the n-th of its stream. The draws go into the engine through its batched model fields
(`Engine.set_model_fields`, the fields it can vary: `variable_fields(m)`) before the engine
resets the world, so that what reset computes (mj_forward) already sees them; start-pose noise
is written after it (`Engine.set_qstate`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import mujoco
import numpy as np

from batchsim.model import RobotSpec, initial_command
from batchsim.types import ConfigurationError
from batchsim.variation.draw import Bound
from batchsim.variation.spec import Variation, load

#: world_params()'s key for each world's start position (qpos), where start-pose noise is drawn
START_QPOS = "start_qpos"


class WorldDraws:
    """The draws of `nworld` worlds of `spec` on an engine that can vary `can` (its
    `variable_fields`); `backend` names it in messages, `who_can(field)` the backends that can."""

    def __init__(
        self,
        spec: RobotSpec,
        nworld: int,
        backend: str,
        can: frozenset[str],
        who_can: Callable[[str], list[str]],
    ):
        self.spec, self.nworld = spec, nworld
        self._backend, self._can, self._who_can = backend, can, who_can
        self.bound: Bound | None = None
        self._first_world = 0
        self._draws = np.full(nworld, -1, np.int64)  # each world's draw number, -1 before its first
        self.params: dict[str, np.ndarray] = {}  # field -> (nworld, *shape) float64: each world's values
        self.start_qpos: np.ndarray | None = None  # (nworld, nq): the start positions drawn

    def set(self, variation: Variation | Any, first_world: int) -> None:
        """Draw from `variation` (a Variation, YAML file or mapping; None: none), world i as world
        `first_world + i` of any fleet. VariationError for a file or name that does not fit the
        model; ConfigurationError for a field this engine cannot vary, naming those that can."""
        if first_world < 0:
            raise ValueError(f"first_world must be >= 0, got {first_world}")
        self.bound = None
        parsed = None if variation is None else load(variation)
        if parsed is None or not parsed.active:
            return
        m = self.spec.mjmodel
        bound = Bound(parsed, m)
        for field in bound.fields:
            if field not in self._can:
                can = self._who_can(field)
                who = f"backends that can: {', '.join(can)}" if can else "no backend can"
                raise ConfigurationError(
                    f"{bound.where[field]}: the {self._backend} backend cannot vary {field} per world; {who}"
                )
        self.bound = bound
        self._first_world = int(first_world)
        self._draws[:] = -1
        self.params = {f: np.zeros((self.nworld, *_shape(m, f))) for f in bound.fields}
        self.start_qpos = None

    def world_params(self, rows: np.ndarray | None) -> dict[str, np.ndarray]:
        """Each world's current values of every varied field (`start_qpos` too where start-pose
        noise is drawn): field -> `(n, *shape)` float64 copies, for worlds `rows` (None: all)."""
        if self.bound is None:
            return {}
        sel = slice(None) if rows is None else rows
        out = {f: v[sel].copy() for f, v in self.params.items()}
        if self.start_qpos is not None:
            out[START_QPOS] = self.start_qpos[sel].copy()
        return out

    def reseed(self, seed: int) -> None:
        """Draw from `seed` from now on: every world's next reset is its first draw again."""
        if self.bound is None:
            return
        if not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"a seed is a non-negative integer, got {seed!r}")
        self.bound = Bound(dataclasses.replace(self.bound.variation, seed=int(seed)), self.spec.mjmodel)
        self._draws[:] = -1

    def draw_numbers(self) -> np.ndarray:
        """(nworld,) int64: how many times each world has drawn since its first (0 at start)."""
        return np.maximum(self._draws, 0) if self.bound is not None else np.zeros(self.nworld, np.int64)

    # --- at a reset ---
    def draw(self, sel: np.ndarray, set_model_fields: Callable[[np.ndarray, dict[str, np.ndarray]], None]) -> None:
        """The listed worlds' draws into the engine (`set_model_fields`), before it resets them:
        their first draw, and with redraw_on_reset a new one at each reset."""
        if self.bound is None:
            return
        if not self.bound.variation.redraw_on_reset:
            sel = sel[self._draws[sel] < 0]
        if not sel.size:
            return
        self._draws[sel] += 1
        values = self.bound.draw(self._first_world + sel, self._draws[sel])
        for field, value in values.items():
            self.params[field][sel] = value
        set_model_fields(sel, self.params)

    def draw_start(self, sel: np.ndarray) -> np.ndarray | None:
        """The listed worlds' start poses drawn (`place_start` writes them once their ctrl is set);
        the commands that hold each world's pose (n, ncommand), as the initial command holds the
        keyframe's (batchsim.model.initial_command); None without start-pose noise."""
        if self.bound is None:
            return None
        spec = self.spec
        initial = spec.initial
        qpos = self.bound.start_qpos(self._first_world + sel, self._draws[sel], initial.qpos)
        if qpos is None:
            return None
        if self.start_qpos is None:
            self.start_qpos = np.broadcast_to(initial.qpos, (self.nworld, len(initial.qpos))).copy()
        self.start_qpos[sel] = qpos
        return np.array([initial_command(spec, q) for q in qpos]).reshape(len(sel), -1)

    def place_start(self, sel: np.ndarray, set_qstate: Callable[[np.ndarray, np.ndarray, np.ndarray], None]) -> None:
        """The listed worlds' drawn start poses into the engine (`set_qstate`), at the initial velocity."""
        if self.start_qpos is None:
            return
        qvel = self.spec.initial.qvel
        set_qstate(sel, self.start_qpos[sel], np.broadcast_to(qvel, (len(sel), len(qvel))).copy())


def _shape(m: mujoco.MjModel, field: str) -> tuple[int, ...]:
    if field.startswith("opt."):
        return (np.asarray(getattr(m.opt, field[4:])).size,)
    return tuple(getattr(m, field).shape)
