"""`ref`: a test-only engine, each world its own MjData stepped by `mujoco.mj_step` in a Python loop.

The proof that a backend is one engine class plus one registry line: conftest.py registers it
(`batchsim.backends.register`) and the contract suite (tests/test_contract.py) runs on it
unchanged. It is also a reference in the plain sense, as mujoco.rollout is tested
against one: nothing batched, nothing clever, MuJoCo's own step per world.

What it states (batchsim.backends): no devices (no `available_devices`), no compile on the first
period, no cameras or lidar rays (the camera and ray hooks are left out), a memory estimate
(`physics_memory`). The rest of the contract (checks, bookkeeping, lifecycle, noise) is
BatchedSystem's, which owns this engine (batchsim.engine).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import mujoco
import numpy as np

from batchsim.engine import Engine
from batchsim.parts.failures import warning_text
from batchsim.plugins.base_velocity import HELD_DOFS, world_velocity
from batchsim.startup import PhysicsMemory, mjdata_bytes
from batchsim.types import READ_FIELDS, HeldBase, Status, StepFailures

_W = mujoco.mjtWarning
# the warnings that make a world untrustworthy, in MuJoCo's order: overflows, then divergence
_OVERFLOW = range(int(_W.mjWARN_CONTACTFULL), int(_W.mjWARN_CNSTRFULL) + 1)
_WATCHED = range(_OVERFLOW.start, int(_W.mjWARN_BADCTRL) + 1)


class ReferenceEngine(Engine):
    """`nworld` MjData, stepped one after another with `mujoco.mj_step`.

    Options:
      deterministic: accepted as every backend accepts it; a loop of mj_step is repeatable.
    """

    name: ClassVar[str] = "ref"
    OPTIONS: ClassVar[dict[str, Any]] = {"deterministic": True}

    logs_failures: ClassVar[bool] = True  # C MuJoCo logs a world's failure itself

    @staticmethod
    def physics_memory(m: mujoco.MjModel, **_: int | None) -> PhysicsMemory:
        """One MjData per world: its arrays and its arena."""
        return PhysicsMemory(mjdata_bytes(m) + int(m.narena))

    # --- the engine ---
    def open(self, *, held_base: HeldBase | None = None, varied: tuple[str, ...] = ()) -> None:
        self._data = [mujoco.MjData(self.model) for _ in range(self.nworld)]
        self._ctrl = np.zeros((self.nworld, self.model.nu))
        self._held_base = held_base
        self._held: np.ndarray | None = None  # the base velocity's target (batchsim.plugins.base_velocity)

    def close(self) -> None:
        del self._data, self._ctrl

    def ctrl(self) -> np.ndarray:
        return self._ctrl

    def upload_ctrl(self) -> None:
        for d, ctrl in zip(self._data, self._ctrl, strict=True):
            d.ctrl[:] = ctrl

    def _fields(self) -> dict[str, np.ndarray]:
        """READ_FIELDS `(nworld, ...)` and `time` `(nworld,)`, copied out of every MjData."""
        fields = {f: np.stack([getattr(d, f) for d in self._data]) for f in READ_FIELDS}
        fields["time"] = np.array([d.time for d in self._data])
        return fields

    def read(self) -> None:
        self.buffers.gather(self._fields())

    def step(
        self, nstep: int, meanwhile: Callable[[], None], start: tuple[np.ndarray, ...] | None
    ) -> StepFailures | None:
        # what a world that fails in this call goes on reading: every world now, before stepping
        start = self.buffers.empty_like()
        self.buffers.gather(self._fields(), start)
        failed: list[tuple[int, Status, str]] = []
        for w in np.flatnonzero(~self.buffers.frozen):
            failure = self._step_world(int(w), nstep)
            if failure is not None:
                failed.append((int(w), *failure))
        if not failed:
            return None
        worlds = np.array([w for w, _, _ in failed], np.int64)
        readings = start[0][worlds]  # a raw gather: the contract finishes it
        status = np.array([s for _, s, _ in failed], np.uint8)
        return StepFailures(worlds, status, [r for _, _, r in failed], readings, start[1][worlds], start[2][worlds])

    def _step_world(self, w: int, nstep: int) -> tuple[Status, str] | None:
        """`nstep` mj_steps of world `w`; how it failed (MuJoCo's first watched warning, or its
        error), or None. MuJoCo resets a diverged world inside mj_step and counts the warning,
        which only mj_resetData clears: a world counted is one that failed in this call."""
        m, d = self.model, self._data[w]
        held = None
        if self._held is not None and not np.isnan(self._held[w, 0]):
            adr = self._held_base.qposadr
            held = world_velocity(d.qpos[None, adr + 3 : adr + 7], self._held[w : w + 1])[0]
        for _ in range(nstep):
            if held is not None:
                d.qvel[self._held_base.dofadr + np.array(HELD_DOFS)] = held
            try:
                mujoco.mj_step(m, d)
            except mujoco.FatalError as e:
                return Status.DIVERGED, str(e)
            counted = [k for k in _WATCHED if d.warning[k].number]
            if counted:
                k = counted[0]  # an overflow before the instability it may have caused
                status = Status.OVERFLOW if k in _OVERFLOW else Status.DIVERGED
                return status, warning_text(k, d.warning[k].lastinfo)
        return None

    def reset(self, worlds: np.ndarray | None) -> None:
        for w in range(self.nworld) if worlds is None else worlds:
            self.spec.initial.apply(self.model, self._data[w])  # mj_resetData, the state, mj_forward

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.stack([self._data[w].xpos for w in worlds]), np.stack([self._data[w].xquat for w in worlds])

    def qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.stack([self._data[w].qpos for w in worlds]), np.stack([self._data[w].qvel for w in worlds])

    def set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        for w, p, v in zip(worlds, qpos, qvel, strict=True):
            d = self._data[w]
            d.qpos[:], d.qvel[:] = p, v
            mujoco.mj_forward(self.model, d)  # poses and sensordata of the new state

    def stage_base_velocity(self, target: np.ndarray) -> None:
        self._held = target.copy()

    def stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        for w, wrench in zip(worlds, xfrc, strict=True):
            self._data[w].xfrc_applied[:] = wrench

    def device_arrays(self) -> dict[str, np.ndarray]:
        """qpos, qvel, qfrc_actuator, sensordata, time: copies out of the worlds' MjData (there
        is no batched array to hand out); ctrl: the host array write() fills."""
        return {**self._fields(), "ctrl": self._ctrl}
