"""The `cpu` engine: MuJoCo 4's threaded batch, `mujoco.batch.Batch`, in exact float64.

Host arrays are the batch's own live bindings, so write() and read() copy nothing but
the interface columns. Results are bit-identical to a loop of `mujoco.mj_step` over one
`MjData` per world, at any thread count.

A world fails when MuJoCo warns about it (mj_checkPos/Vel/Acc: NaN, inf or beyond mjMAXVAL;
a full contact or constraint buffer) or raises in it. MuJoCo has by then reset it inside the
step, so what it reads frozen comes from before the step() call: the host readings, when
read() ran since the last step (the control loop's order), else a gather made just before
stepping.

Body poses (`body_poses()`) are the batch's `xpos`/`xquat` outputs, bound at the first call
(a bound output is copied out of every world at every step from then on, so not before). Until
the batch's next call on a world fills them, that world's come from mj_kinematics of its
current state: exact when the first call follows configure() or reset(), one substep ahead of
the contract's "before the last substep" when it follows a step().
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, ClassVar

import mujoco
import numpy as np
from mujoco import batch as mjbatch

from batchsim.backends import footprint
from batchsim.backends.host_sensors import HostSensors
from batchsim.engine import INTEGRATION, Engine
from batchsim.parts.failures import warning_text
from batchsim.plugins.base_velocity import HELD_DOFS, world_velocity
from batchsim.sensors import Camera, Lidar
from batchsim.types import HeldBase, Status, StepFailures

_W = mujoco.mjtWarning
# MuJoCo warnings that mean a world's numbers can no longer be trusted (mjWARN_INERTIA is
# a model property, not a world's): the overflow and instability warnings are contiguous
_OVERFLOW_WARNINGS = slice(int(_W.mjWARN_CONTACTFULL), int(_W.mjWARN_CNSTRFULL) + 1)
_DIVERGED_WARNINGS = slice(int(_W.mjWARN_BADQPOS), int(_W.mjWARN_BADCTRL) + 1)
_WATCHED = slice(_OVERFLOW_WARNINGS.start, _DIVERGED_WARNINGS.stop)
assert _OVERFLOW_WARNINGS.stop == _DIVERGED_WARNINGS.start
_DEVICE_ARRAYS = ("qpos", "qvel", "qfrc_actuator", "sensordata", "time")
# MjData's fields of mjSTATE_INTEGRATION (set_physics_state writes each into the batch's rows)
_STATE_FIELDS = (
    "time", "qpos", "qvel", "act", "qacc_warmstart", "ctrl", "qfrc_applied", "xfrc_applied", "eq_active",
    "mocap_pos", "mocap_quat", "userdata", "plugin_state",
)  # fmt: skip


class CpuEngine(Engine):
    """`nworld` worlds on `mujoco.batch.Batch`, stepped on `nthread` threads.

    Options:
      nthread: worker threads, including the caller's; 0 means one per CPU core, capped
        at nworld.
      deterministic: accepted for a make() call that works on every backend; MuJoCo on
        the CPU is bitwise repeatable whatever it says.
    """

    name: ClassVar[str] = "cpu"
    OPTIONS: ClassVar[dict[str, Any]] = {"nthread": 0, "deterministic": True}
    OPTION_MINIMA: ClassVar[dict[str, float]] = {"nthread": 0}
    physics_memory = staticmethod(footprint.cpu)
    logs_failures: ClassVar[bool] = True  # C MuJoCo logs a world's failure itself (MUJOCO_LOG.TXT)

    def open(self, *, held_base: HeldBase | None = None, varied: tuple[str, ...] = ()) -> None:
        nthread = int(self.options["nthread"]) or min(self.nworld, os.cpu_count() or 1)
        self._batch = mjbatch.Batch(self.model, self.nworld, nthread=nthread)
        b = self._batch
        self._fields = {f: b.bind(f) for f in _DEVICE_ARRAYS}
        self._ctrl = b.bind("ctrl")
        self._warnings = b.warning  # (nworld, mjNWARNING, 2) live: lastinfo, number
        self._warning_count = b.warning[:, :, 1]
        self.nthread = b.nthread
        # readings at the start of a step() that follows another without a read() in between
        self._start = self.buffers.empty_like()
        self._held_base = held_base
        self._held: np.ndarray | None = None  # the base velocity's target (batchsim.plugins.base_velocity)

    def close(self) -> None:
        del self._batch, self._fields, self._ctrl, self._warnings, self._warning_count, self._start
        self._poses = self._unfilled = None

    def ctrl(self) -> np.ndarray:
        return self._ctrl

    def read(self) -> None:
        self.buffers.gather(self._fields)

    def step(
        self,
        nstep: int,
        meanwhile: Callable[[], None],
        start: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> StepFailures | None:
        frozen = self.buffers.frozen
        if start is None:  # no read() since the last step: gather the start now
            start = self._start
            self.buffers.gather(self._fields, start)
        errors: dict[int, str] = {}
        if self._unfilled is not None:  # the stepped worlds' bound poses get filled by this call
            self._unfilled &= frozen
        ids = np.flatnonzero(~frozen).astype(np.int32) if frozen.any() else None
        if self._held is not None:
            errors = self._step_held(ids, nstep)
        elif ids is None or ids.size:
            try:
                self._batch.step(ids=ids, nstep=nstep)
            except mjbatch.SimulationError as e:
                # mju_error in some worlds: they kept their state from before the call, the others ran
                errors = {int(w): self._batch.error(int(w)) for w in e.ids}
        return self._failures(frozen, errors, start)

    def stage_base_velocity(self, target: np.ndarray) -> None:
        self._held = target.copy()

    def stage_xfrc(self, worlds: np.ndarray, xfrc: np.ndarray) -> None:
        self._batch.bind("xfrc_applied")[worlds] = xfrc  # a state field: the rows themselves, bound once

    def _step_held(self, ids: np.ndarray | None, nstep: int) -> dict[int, str]:
        """`nstep` substeps of the worlds `ids` (None: all), one batch call each, the base's planar
        velocity written into qvel before each (batchsim.plugins.base_velocity); the worlds that raised."""
        drive = self._held_base
        qpos, qvel = self._fields["qpos"], self._fields["qvel"]
        held = world_velocity(qpos[:, drive.qposadr + 3 : drive.qposadr + 7], self._held)
        rows = np.flatnonzero(~np.isnan(held[:, 0]))
        at, held = np.ix_(rows, drive.dofadr + np.array(HELD_DOFS)), held[rows]
        errors: dict[int, str] = {}
        for _ in range(nstep):
            if ids is not None and not ids.size:
                break
            qvel[at] = held
            try:
                self._batch.step(ids=ids, nstep=1)
            except mjbatch.SimulationError as e:
                # mju_error in some worlds: they kept their state from before this substep, the others go on
                errors.update({int(w): self._batch.error(int(w)) for w in e.ids})
                ids = np.setdiff1d(np.arange(self.nworld) if ids is None else ids, e.ids).astype(np.int32)
        return errors

    def _failures(
        self,
        frozen: np.ndarray,
        errors: dict[int, str],
        start: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> StepFailures | None:
        """The worlds that tripped a MuJoCo instability or overflow warning, or raised, in this call.

        MuJoCo checks qpos, qvel and qacc for NaN, inf and huge values at every step
        (mj_checkPos/Vel/Acc), resets a world that fails and counts the warning, so the
        counters, which only mj_resetData clears, catch every divergence; a world counted
        before this call is frozen already.
        """
        count = self._warning_count
        if not errors and not count[:, _WATCHED].any():
            return None
        failed = count[:, _WATCHED].any(axis=1) & ~frozen
        failed[list(errors)] = True
        worlds = np.flatnonzero(failed)
        if not worlds.size:
            return None
        status = np.zeros(worlds.size, np.uint8)
        reasons = []
        for k, w in enumerate(worlds):
            kinds = np.flatnonzero(count[w, _WATCHED]) + _WATCHED.start
            if w in errors or kinds.size == 0:
                status[k] = Status.DIVERGED
                reasons.append(errors.get(int(w), "MuJoCo error"))
                continue
            warning = int(kinds[0])  # an overflow before the instability it may have caused
            overflow = warning < _OVERFLOW_WARNINGS.stop
            status[k] = Status.OVERFLOW if overflow else Status.DIVERGED
            reasons.append(warning_text(warning, int(self._warnings[w, warning, 0])))
        readings, sensordata, time = start
        finished = readings is not self._start[0]  # read()'s rows are finished; a gather of ours is raw
        return StepFailures(worlds, status, reasons, readings[worlds], sensordata[worlds], time[worlds], finished)

    def device_arrays(self) -> dict[str, np.ndarray]:
        """The batch's live arrays, zero copy, as the GPU backends hand out theirs: qpos, qvel,
        qfrc_actuator, sensordata, ctrl `(nworld, ...)` and time `(nworld,)`, float64 host memory.

        They change in place at every step(); qfrc_actuator and sensordata are read-only.
        """
        return {**self._fields, "ctrl": self._ctrl}

    @classmethod
    def variable_fields(cls, m: mujoco.MjModel) -> frozenset[str]:
        """What mujoco.batch expands per simulation (its MODEL_FIELDS), asset data aside."""
        return frozenset(f for f in mjbatch.MODEL_FIELDS if f.startswith("opt.") or isinstance(getattr(m, f, None), np.ndarray))

    def set_model_fields(self, worlds: np.ndarray, params: dict[str, np.ndarray]) -> None:
        for field, values in params.items():
            self._batch.expand(field)[worlds] = values[worlds]

    def reset(self, worlds: np.ndarray | None) -> None:
        ids = None if worlds is None else np.sort(worlds).astype(np.int32)  # mujoco.batch takes them ascending
        if self._unfilled is not None:
            self._unfilled[slice(None) if worlds is None else worlds] = False
        initial = self.spec.initial
        if initial.is_qpos0 and initial.time == 0.0:
            self._batch.reset(ids=ids)
            return
        # a keyframe, initial values or a start time: the model's defaults, overwritten, then mj_forward
        self._batch.reset(ids=ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        rows = slice(None) if worlds is None else worlds
        for field in ("qpos", "qvel", "act", "ctrl", "mocap_pos", "mocap_quat"):
            value = getattr(initial, field)
            if value.size:
                self._batch.bind(field)[rows] = value
        self._fields["time"][rows] = initial.time
        self._batch.forward(ids=ids)

    # --- body poses: xpos and xquat, bound on the first body_poses() ---
    _poses: tuple[np.ndarray, np.ndarray] | None = None
    _unfilled: np.ndarray | None = None  # (nworld,) bool: rows the batch has not filled since binding

    def body_poses(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._poses is None:
            # bound only when asked for: a bound output is copied out of every world at every call
            self._poses = (self._batch.bind("xpos"), self._batch.bind("xquat"))
            self._unfilled = np.ones(self.nworld, bool)
        xpos, xquat = (a[worlds] for a in self._poses)
        if self._unfilled is not None:
            if not self._unfilled.any():
                self._unfilled = None
            else:  # zero until the batch's next call on them: the current state's kinematics, this once
                self._kinematics_now(worlds, self._unfilled[worlds], xpos, xquat)
        return xpos, xquat

    def pose_rows(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self._poses is None or (self._unfilled is not None and self._unfilled.any()):
            return None  # not bound yet, or rows the batch has not filled: body_poses computes them
        self._unfilled = None
        return self._poses

    def qstate(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._fields["qpos"][worlds], self._fields["qvel"][worlds]  # fancy indexing: copies

    def set_qstate(self, worlds: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        self._fields["qpos"][worlds] = qpos
        self._fields["qvel"][worlds] = qvel
        self._batch.forward(ids=np.sort(worlds).astype(np.int32))  # poses and sensordata of the new state

    def physics_state(self, worlds: np.ndarray, what: int = INTEGRATION) -> np.ndarray:
        """Exact: each world's MjData out of the batch, then mj_getState."""
        m = self.model
        d = mujoco.MjData(m)
        out = np.empty((len(worlds), mujoco.mj_stateSize(m, what)))
        for k, w in enumerate(worlds):
            self._batch.get_data(int(w), d)
            mujoco.mj_getState(m, d, out[k], what)
        return out

    def set_physics_state(self, worlds: np.ndarray, states: np.ndarray) -> None:
        """Through a MjData per world: mj_setState, then its state fields into the batch's rows."""
        m = self.model
        d = mujoco.MjData(m)
        for k, w in enumerate(worlds):
            self._batch.get_data(int(w), d)
            mujoco.mj_setState(m, d, states[k], INTEGRATION)
            for field in _STATE_FIELDS:
                value = getattr(d, field)
                if np.size(value):
                    self._batch.bind(field)[int(w)] = value
        self._batch.forward(ids=np.sort(worlds).astype(np.int32))

    def _kinematics_now(self, worlds: np.ndarray, rows: np.ndarray, xpos: np.ndarray, xquat: np.ndarray) -> None:
        """xpos/xquat of the current state into the `rows` (bool) of `worlds`: mj_kinematics per world."""
        m = self.model
        d = mujoco.MjData(m)
        for k in np.flatnonzero(rows):
            self._batch.get_data(int(worlds[k]), d)
            mujoco.mj_kinematics(m, d)
            xpos[k], xquat[k] = d.xpos, d.xquat

    # --- cameras and lidars: MuJoCo's renderer and the batch's threaded ray casting ---
    _host: HostSensors | None = None  # made on the first render or scan

    def _host_sensors(self) -> HostSensors:
        if self._host is None:
            self._host = HostSensors(self.model, self._batch)
        return self._host

    def render_frames(self, camera: Camera, worlds: np.ndarray, copy: bool) -> tuple[np.ndarray, np.ndarray]:
        return self._host_sensors().frames(camera, worlds, copy)

    def prepare_rendering(self, cameras: list[Camera]) -> None:
        self._host_sensors().prepare(cameras)

    def render_frames_later(self, camera: Camera, worlds: np.ndarray) -> Future:
        return self._host_sensors().submit(camera, worlds)  # drawn on the render thread while the caller steps on

    def cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        return self._host_sensors().cast(lidar, worlds)

    def close_sensors(self) -> None:
        if self._host is not None:
            self._host.close()
            self._host = None
