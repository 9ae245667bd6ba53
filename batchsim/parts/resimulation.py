"""What re-simulation (batchsim.resim) asks of a system, as part of BatchedSystem: each world's
whole physics state and the inputs its steps take (what a recording keeps), and the same written
back into a world (what a re-run with its controllers starts from)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import mujoco
import numpy as np

from batchsim.parts.face import RUNNING
from batchsim.types import worlds_index

_XFRC = int(mujoco.mjtState.mjSTATE_XFRC_APPLIED)


class Resimulation:
    """BatchedSystem's re-simulation calls (it has `engine`, `parts`, `model`, `nworld`, `read`)."""

    engine: Any
    parts: Any
    model: mujoco.MjModel
    nworld: int

    def _rows_of(self, worlds: Sequence[int] | np.ndarray | None) -> np.ndarray:
        rows = worlds_index(worlds, self.nworld)
        return np.arange(self.nworld) if rows is None else rows

    def physics_state(self, worlds: Sequence[int] | np.ndarray) -> np.ndarray:
        """The listed worlds' whole physics state `(n, mj_stateSize(model, INTEGRATION))` float64, laid
        out as `mujoco.mj_getState(..., mjSTATE_INTEGRATION)` lays it out: what stepping them needs
        (time, qpos, qvel, act, warmstart, ctrl, applied forces, mocap, ...). Exact on cpu; a GPU
        engine's time, qpos, qvel and ctrl (float32 made float64) over the model's defaults."""
        self._require("read the physics state", RUNNING)
        return self.engine.physics_state(self._rows_of(worlds))

    def physics_inputs(self, worlds: Sequence[int] | np.ndarray | None = None) -> dict[str, np.ndarray]:
        """What the listed worlds' physics takes in the steps that follow a write(), beyond its state:
        `ctrl` `(n, nu)` (after the PIDs and transmissions), and where the plugins run
        `base_velocity` `(n, 3)` (the held body-frame vx, vy, wz; NaN: none held) and `xfrc_applied`
        `(n, nbody * 6)`. float64 copies, for all (None) or the listed worlds (re-simulation records
        them: batchsim.resim)."""
        rows = worlds_index(worlds, self.nworld)  # None: every world, no index array (every period while recording)
        take = slice(None) if rows is None else rows
        out = {"ctrl": self.engine.ctrl()[take].astype(np.float64)}
        drive = self.parts.base_drive
        if drive.velocity is not None:
            n = self.nworld if rows is None else len(rows)
            out["base_velocity"] = np.full((n, 3), np.nan) if drive.staged is None else drive.staged[take].copy()
        if self.parts.wrenches.configured:
            out["xfrc_applied"] = self.engine.physics_state(self._rows_of(worlds), _XFRC)
        return out

    def set_physics_state(self, worlds: Sequence[int] | np.ndarray, states: Any) -> None:
        """Write whole physics states `(n, nstate)` (physics_state's layout) into the listed worlds,
        then read() them; cpu only (NotImplementedError elsewhere)."""
        self._require("write the physics state", RUNNING)
        rows = self._rows_of(worlds)
        states = np.asarray(states, np.float64).reshape(len(rows), -1)
        want = mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_INTEGRATION)
        if states.shape[1] != want:
            raise ValueError(f"a physics state has {want} values (mjSTATE_INTEGRATION), got {states.shape[1]}")
        self.engine.set_physics_state(rows, states)
        self.read()

    def set_world_params(self, worlds: Sequence[int] | np.ndarray, params: Mapping[str, Any]) -> None:
        """Give the listed worlds these model values (world_params' fields: field -> `(n, *shape)`),
        the other worlds keeping theirs; as a variation's draws are applied, before a reset."""
        rows = self._rows_of(worlds)
        current = self.parts.draws.params
        full = {}
        for field, value in params.items():
            if field in current:
                array = current[field]
            else:
                nominal = np.asarray(getattr(self.model.opt, field[4:]) if field.startswith("opt.") else getattr(self.model, field))
                array = np.broadcast_to(nominal.astype(np.float64), (self.nworld, *nominal.shape)).copy()
            array[rows] = np.asarray(value, np.float64).reshape(len(rows), *array.shape[1:])
            full[field] = array
        if full:
            self.engine.set_model_fields(rows, full)
