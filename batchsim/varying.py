"""Per-world randomization in the contract: `set_variation`, `world_params`, and the draws at reset.

Mixed into BatchedSystem. A Variation (batchsim.variation) is given before configure; each
world draws at its first reset (configure's) and, with `redraw_on_reset`, again at each reset
that lists it, its n-th draw the n-th of its stream. The draws go into the engine through the
backend's batched model fields (the engine hook `_set_model_fields`, and the fields a backend
can vary, `variable_fields(m)`), before the engine resets the world, so that what reset
computes (mj_forward) already sees them; start-pose noise is written after it (`_set_qstate`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from batchsim.lifecycle import LifecycleError, LifecycleState
from batchsim.model import initial_command
from batchsim.types import ConfigurationError
from batchsim.variation import Bound, Variation, VariationError, load

#: world_params()'s key for each world's start position (qpos), where start-pose noise is drawn
START_QPOS = "start_qpos"


class Varying:
    """The contract's randomization: hooks and state that BatchedSystem's reset calls."""

    _bound: Bound | None = None
    _first_world = 0
    _draws: np.ndarray  # (nworld,) int64: each world's draw number, -1 before its first
    _params: dict[str, np.ndarray]  # field -> (nworld, *shape) float64: each world's current values
    _start_qpos: np.ndarray | None = None  # (nworld, nq) the start positions drawn, with start-pose noise

    @classmethod
    def variable_fields(cls, m: mujoco.MjModel) -> frozenset[str]:
        """The model fields this backend can give per-world values (`opt.<name>` for options)."""
        return frozenset()

    def set_variation(
        self, variation: Variation | str | Path | Mapping[str, Any] | None, first_world: int = 0
    ) -> None:
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
        if getattr(self, "_opened", False) or self.lifecycle_state not in (LifecycleState.UNCONFIGURED,):
            raise LifecycleError(
                "set the variation before configure(): the worlds draw when they are allocated"
            )
        if first_world < 0:
            raise ValueError(f"first_world must be >= 0, got {first_world}")
        if variation is None:
            self._bound = None
            return
        parsed = load(variation)
        if not parsed.active:
            self._bound = None
            return
        bound = Bound(parsed, self.model)
        can = self.variable_fields(self.model)
        for field in bound.fields:
            if field not in can:
                raise ConfigurationError(
                    f"{bound.where[field]}: the {self.name} backend cannot vary {field} per world; "
                    f"{_backends_that_can(field, self.model)}"
                )
        self._bound = bound
        self._first_world = int(first_world)
        self._draws = np.full(self.nworld, -1, np.int64)
        self._params = {f: np.zeros((self.nworld, *_shape(self.model, f))) for f in bound.fields}
        self._start_qpos = None

    @property
    def variation(self) -> Variation | None:
        """The Variation the worlds draw from, or None."""
        return None if self._bound is None else self._bound.variation

    @property
    def variation_bound(self) -> Bound | None:
        """The variation as resolved against this model (what a draw writes, and how), or None."""
        return self._bound

    def world_params(self, worlds: Sequence[int] | np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Each world's current values of every varied field: field -> `(n, *shape)` float64 copies,
        for all or the listed worlds; `start_qpos` `(n, nq)` too where start-pose noise is drawn.
        Empty without a variation. Valid from configure on."""
        if self._bound is None:
            return {}
        if not getattr(self, "_opened", False):
            raise LifecycleError("world_params(): the worlds draw at configure(); configure first")
        rows = self._worlds(worlds)  # type: ignore[attr-defined]
        sel = slice(None) if rows is None else rows
        out = {f: v[sel].copy() for f, v in self._params.items()}
        if self._start_qpos is not None:
            out[START_QPOS] = self._start_qpos[sel].copy()
        return out

    def reseed(self, seed: int) -> None:
        """Draw from `seed` from now on, as a new run would: every world's next reset is its
        first draw again (a gymnasium `reset(seed=...)`). Nothing changes until a reset."""
        if self._bound is None:
            return
        if not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"a seed is a non-negative integer, got {seed!r}")
        self._bound = Bound(dataclasses.replace(self._bound.variation, seed=int(seed)), self.model)
        self._draws[:] = -1

    def draw_numbers(self) -> np.ndarray:
        """(nworld,) int64: how many times each world has drawn since its first (0 at start)."""
        return np.maximum(self._draws, 0) if self._bound is not None else np.zeros(self.nworld, np.int64)

    # --- called by reset() ---
    def _vary(self, sel: np.ndarray) -> None:
        """The listed worlds' draws into the engine, before it resets them: their first draw,
        and with redraw_on_reset a new one at each reset."""
        if self._bound is None:
            return
        if not self._bound.variation.redraw_on_reset:
            sel = sel[self._draws[sel] < 0]
        if not sel.size:
            return
        self._draws[sel] += 1
        values = self._bound.draw(self._first_world + sel, self._draws[sel])
        for field, value in values.items():
            self._params[field][sel] = value
        self._set_model_fields(sel, self._params)

    def _vary_start(self, sel: np.ndarray) -> np.ndarray | None:
        """The listed worlds' start poses drawn (`_place_start` writes them, once their ctrl is
        set); the commands that hold each world's pose (n, ncommand), as the initial command
        holds the keyframe's (batchsim.model.initial_command); None without start-pose noise."""
        if self._bound is None:
            return None
        spec = self.spec  # type: ignore[attr-defined]
        initial = spec.initial
        qpos = self._bound.start_qpos(self._first_world + sel, self._draws[sel], initial.qpos)
        if qpos is None:
            return None
        if self._start_qpos is None:
            self._start_qpos = np.broadcast_to(initial.qpos, (self.nworld, len(initial.qpos))).copy()
        self._start_qpos[sel] = qpos
        return np.array([initial_command(spec, q) for q in qpos]).reshape(len(sel), -1)

    def _place_start(self, sel: np.ndarray) -> None:
        """The listed worlds' drawn start poses into the engine, at the initial velocity."""
        if self._start_qpos is None:
            return
        qvel = self.spec.initial.qvel  # type: ignore[attr-defined]
        self._set_qstate(sel, self._start_qpos[sel], np.broadcast_to(qvel, (len(sel), len(qvel))).copy())

    # --- the engine hook ---
    def _set_model_fields(self, worlds: np.ndarray, params: dict[str, np.ndarray]) -> None:
        """Make `params[field][worlds]` the engine's values of each field for those worlds.
        `params` holds every world's (field -> (nworld, *shape) float64), the listed rows new;
        a backend may upload whole arrays. Called before the engine resets those worlds."""
        raise NotImplementedError(f"the {self.name} backend cannot vary model fields per world")


def _shape(m: mujoco.MjModel, field: str) -> tuple[int, ...]:
    if field.startswith("opt."):
        return (np.asarray(getattr(m.opt, field[4:])).size,)
    return tuple(getattr(m, field).shape)


def _backends_that_can(field: str, m: mujoco.MjModel) -> str:
    from batchsim.backends import varying_backends  # the registry sits above the contract

    can = varying_backends(field, m)
    return f"backends that can: {', '.join(can)}" if can else "no backend can"


__all__ = ["START_QPOS", "Varying", "VariationError"]
