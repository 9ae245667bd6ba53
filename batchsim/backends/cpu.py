"""The `cpu` backend: MuJoCo 4's threaded batch, `mujoco.batch.Batch`, in exact float64.

Host arrays are the batch's own live bindings, so write() and read() copy nothing but
the interface columns. Results are bit-identical to a loop of `mujoco.mj_step` over one
`MjData` per world, at any thread count.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, ClassVar

import mujoco
import numpy as np
from mujoco import batch as mjbatch

from batchsim.hardware import BatchedSystem, Status
from batchsim.sensors import Camera, Lidar
from batchsim.sensors.host import HostSensors

_W = mujoco.mjtWarning
# MuJoCo warnings that mean a world's numbers can no longer be trusted (mjWARN_INERTIA is
# a model property, not a world's): the overflow and instability warnings are contiguous
_OVERFLOW_WARNINGS = slice(int(_W.mjWARN_CONTACTFULL), int(_W.mjWARN_CNSTRFULL) + 1)
_DIVERGED_WARNINGS = slice(int(_W.mjWARN_BADQPOS), int(_W.mjWARN_BADCTRL) + 1)
_WATCHED = slice(_OVERFLOW_WARNINGS.start, _DIVERGED_WARNINGS.stop)
assert _OVERFLOW_WARNINGS.stop == _DIVERGED_WARNINGS.start


class CpuSystem(BatchedSystem):
    """`nworld` worlds on `mujoco.batch.Batch`, stepped on `nthread` threads.

    Options:
      nthread: worker threads, including the caller's; 0 means one per CPU core, capped
        at nworld.
      deterministic: accepted for a make() call that works on every backend; MuJoCo on
        the CPU is bitwise repeatable whatever it says.
    """

    name: ClassVar[str] = "cpu"
    OPTIONS: ClassVar[dict[str, Any]] = {"nthread": 0, "deterministic": True}

    def _open(self) -> None:
        nthread = int(self.options["nthread"]) or min(self.nworld, os.cpu_count() or 1)
        self._batch = mjbatch.Batch(self.model, self.nworld, nthread=nthread)
        b = self._batch
        self._fields = {
            "qpos": b.bind("qpos"),
            "qvel": b.bind("qvel"),
            "qfrc_actuator": b.bind("qfrc_actuator"),
            "sensordata": b.bind("sensordata"),
            "time": b.bind("time"),
        }
        self._ctrl = b.bind("ctrl")
        self._warning_count = b.warning[:, :, 1]  # (nworld, mjNWARNING) live counters
        self.nthread = b.nthread

    def _close(self) -> None:
        del self._batch, self._fields, self._ctrl, self._warning_count

    def _ctrl_host(self) -> np.ndarray:
        return self._ctrl

    def _download(self) -> Mapping[str, np.ndarray]:
        return self._fields

    def _step(self, nstep: int) -> None:
        frozen = self.frozen
        try:
            if not frozen.any():
                self._batch.step(nstep=nstep)
            elif not frozen.all():
                self._batch.step(ids=np.flatnonzero(~frozen).astype(np.int32), nstep=nstep)
        except mjbatch.SimulationError as e:
            # mju_error in some worlds: they kept their previous state, the others ran
            self.status[e.ids] |= np.uint8(Status.DIVERGED)
        self._check_worlds()

    def _check_worlds(self) -> None:
        """Freeze the worlds that tripped a MuJoCo instability or overflow warning.

        MuJoCo checks qpos, qvel and qacc for NaN, inf and huge values at every step
        (mj_checkPos/Vel/Acc), resets a world that fails and counts the warning, so the
        counters, which only mj_resetData clears, catch every divergence.
        """
        count = self._warning_count
        if not count[:, _WATCHED].any():
            return
        diverged = count[:, _DIVERGED_WARNINGS].any(axis=1)
        overflow = count[:, _OVERFLOW_WARNINGS].any(axis=1)
        self.status[diverged] |= np.uint8(Status.DIVERGED)
        self.status[overflow] |= np.uint8(Status.OVERFLOW)

    def device_arrays(self) -> dict[str, np.ndarray]:
        """The batch's live arrays, zero copy, as the GPU backends hand out theirs: qpos, qvel,
        qfrc_actuator, sensordata, ctrl `(nworld, ...)` and time `(nworld,)`, float64 host memory.

        They change in place at every step(); qfrc_actuator and sensordata are read-only.
        """
        return {**self._fields, "ctrl": self._ctrl}

    def _reset(self, worlds: np.ndarray | None) -> None:
        ids = None if worlds is None else worlds.astype(np.int32)
        initial = self.spec.initial
        if initial.source == "qpos0":
            self._batch.reset(ids=ids)
            return
        # a keyframe or initial values: the model's defaults, overwritten, then mj_forward
        self._batch.reset(ids=ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        rows = slice(None) if worlds is None else worlds
        for field in ("qpos", "qvel", "act", "ctrl", "mocap_pos", "mocap_quat"):
            value = getattr(initial, field)
            if value.size:
                self._batch.bind(field)[rows] = value
        self._fields["time"][rows] = initial.time
        self._batch.forward(ids=ids)

    # --- cameras and lidars: MuJoCo's renderer and the batch's threaded ray casting ---
    _host: HostSensors | None = None  # made on the first render or scan

    def _host_sensors(self) -> HostSensors:
        if self._host is None:
            self._host = HostSensors(self.model, self._batch)
        return self._host

    def _render_frames(self, camera: Camera, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._host_sensors().frames(camera, worlds)

    def _cast_rays(self, lidar: Lidar, worlds: np.ndarray) -> np.ndarray:
        return self._host_sensors().cast(lidar, worlds)

    def _close_sensors(self) -> None:
        if self._host is not None:
            self._host.close()
            self._host = None
