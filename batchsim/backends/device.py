"""What the device engines (`mjx`, `warp`) share: one base class, no JAX or Warp here.

Both step every world at once in float32 on an accelerator (or JAX's and Warp's CPU
devices), so they cannot skip a frozen world as cpu does: a world that fails is *parked*,
reset on the device with its ctrl held at zero, while read() shows what it held (the
contract's rule, batchsim.parts.readings). Failures are found on the device, once per
control period, and come back as one integer per world (`failure_code`), with the MuJoCo
warning and the entry of the first bad value, so that the log line reads as cpu's does.

An engine built on this class implements `_put_model` (the model on the device, raising
NotImplementedError for a feature the engine lacks), `_reset_on_device`, and the Engine's own
calls (`open`, `close`, `ctrl`, `upload_ctrl`, `read`, `step`).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from batchsim.backends import unsupported_error
from batchsim.engine import Engine
from batchsim.model import RobotSpec
from batchsim.parts.failures import warning_text
from batchsim.types import Status

#: the live arrays `device_arrays()` hands out, `(nworld, ...)` each, `time` `(nworld,)`
DEVICE_ARRAYS = ("qpos", "qvel", "qfrc_actuator", "sensordata", "ctrl", "time")

# A world's failure code, computed on the device: Status bits, then which field went bad
# first (MuJoCo's own order of checks: qpos, qvel, qacc) and at which entry. Below 2**24,
# so that it is exact as a float32 too (mjx returns it in its float32 readings).
STATUS_BITS = 2
FIELD_SHIFT = 2  # 1 qpos, 2 qvel, 3 qacc; 0 none
INDEX_SHIFT = 4
MAX_INDEX = (1 << (24 - INDEX_SHIFT)) - 1
_FIELD_WARNING = {
    1: mujoco.mjtWarning.mjWARN_BADQPOS,
    2: mujoco.mjtWarning.mjWARN_BADQVEL,
    3: mujoco.mjtWarning.mjWARN_BADQACC,
}


def failure_code(status: int, field: int = 0, index: int = 0) -> int:
    """The code a device check writes for one world (the kernels inline the same arithmetic)."""
    return status | (field << FIELD_SHIFT) | (min(index, MAX_INDEX) << INDEX_SHIFT)


def divergence_reason(code: int) -> str:
    """What a failure code says about the divergence, in MuJoCo's words."""
    field = (int(code) >> FIELD_SHIFT) & 3
    if field == 0:
        return "NaN, inf or a value beyond 1e10 in its state"
    return warning_text(_FIELD_WARNING[field], int(code) >> INDEX_SHIFT)


def code_status(codes: np.ndarray) -> np.ndarray:
    """The Status bits of failure codes, (n,) uint8."""
    return (np.asarray(codes).astype(np.int64) & ((1 << STATUS_BITS) - 1)).astype(np.uint8)


class DeviceEngine(Engine):
    """The base of the engines that step every world on a device, in float32.

    Attributes (beyond Engine's):
      device: the engine's device (a JAX or Warp device object).
    """

    compiles_first_period = True  # jax.jit compiles, Warp captures its graph, on the first period
    steps_on_device = True  # step()'s `meanwhile` runs between the period's launch and its wait
    device_dtype = np.float32
    device_is_host = False

    def __init__(self, spec: RobotSpec, nworld: int, **options: Any):
        super().__init__(spec, nworld, **options)
        self.device = self._resolve_device(self.options.get("device"))
        try:
            self._model_on_device = self._put_model(self.model, self.device)
        except NotImplementedError as e:
            raise unsupported_error(self.name, spec, _feature(e)) from None

    @classmethod
    def unsupported(cls, spec: RobotSpec, device: Any = None) -> str | None:
        """The model feature this backend cannot simulate, or None."""
        try:
            cls._put_model(spec.mjmodel, cls._resolve_device(device))
        except NotImplementedError as e:
            return _feature(e)
        return None

    # --- what each device engine supplies ---
    @staticmethod
    def _resolve_device(option: Any) -> Any:
        """The device for the `device` option (None: the engine's default)."""
        raise NotImplementedError

    @staticmethod
    def _put_model(m: mujoco.MjModel, device: Any) -> Any:
        """The model on the device; NotImplementedError names a feature the engine lacks."""
        raise NotImplementedError

    def _reset_on_device(self, worlds: np.ndarray | None) -> None:
        """Put the listed worlds (None: all) at `spec.initial` on the device, clock included."""
        raise NotImplementedError

    # --- shared ---
    def _initial_data(self) -> mujoco.MjData:
        """An MjData at `spec.initial`, mj_forward run: a reset world reads what cpu's reads."""
        mjd = mujoco.MjData(self.model)
        self.spec.initial.apply(self.model, mjd)
        return mjd

    def reset(self, worlds: np.ndarray | None) -> None:
        self._reset_on_device(worlds)  # status is clear: they are live again

    def park(self, worlds: np.ndarray) -> None:
        self._reset_on_device(worlds)
        self.upload_ctrl()  # frozen rows go up as zero

    def _failure_reasons(self, codes: np.ndarray, overflow: Any = None) -> list[str]:
        """One reason per failed world from its failure code; `overflow(i)` says why the i-th
        overflowed, where the backend can tell."""
        reasons = []
        for i, code in enumerate(np.asarray(codes).astype(np.int64)):
            if code & Status.DIVERGED or overflow is None:
                reasons.append(divergence_reason(int(code)))
            else:
                reasons.append(overflow(i))
        return reasons


def _feature(e: NotImplementedError) -> str:
    return str(e).strip().rstrip(".") or type(e).__name__
