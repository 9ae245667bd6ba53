"""The device path on MuJoCo Warp (`DeviceIO`: the engine's `device_state` and `write_device`): the
state gathered and signed into a float32 device buffer, commands written into the simulation's
ctrl, by kernels; no host copy."""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from batchsim.backends.warp.transfers import Transfers
from batchsim.backends.warp.worlds import DeviceWorlds


@wp.kernel
def signed_columns(
    state_in: wp.array2d(dtype=wp.float64),
    sign: wp.array(dtype=wp.float32),
    state_out: wp.array2d(dtype=wp.float32),
):
    """The first state_out.shape[1] gathered columns, each times its sign, in float32."""
    w, c = wp.tid()
    state_out[w, c] = wp.float32(state_in[w, c]) * sign[c]


@wp.kernel
def command_to_ctrl(
    command_in: wp.array2d(dtype=Any),
    actuator: wp.array(dtype=wp.int32),
    parked: wp.array(dtype=wp.int32),
    ctrl_kept: wp.array2d(dtype=wp.float32),
    ctrl_out: wp.array2d(dtype=wp.float32),
):
    """ctrl[w, actuator[c]] = command[w, c], and into the kept copy of ctrl that resets and
    parks upload from (warp/transfers.py); a parked world's ctrl stays zero."""
    w, c = wp.tid()
    x = wp.float32(command_in[w, c])
    ctrl_kept[w, actuator[c]] = x
    if parked[w] != 0:
        ctrl_out[w, actuator[c]] = wp.float32(0.0)
    else:
        ctrl_out[w, actuator[c]] = x


class DeviceIO:
    """The state gathered and signed on the device, into one buffer kept for it, and commands
    written into ctrl there."""

    def __init__(self, worlds: DeviceWorlds, transfers: Transfers):
        self._worlds, self._transfers = worlds, transfers
        self._out: wp.array | None = None  # (nworld, nstate) float32
        self._sign: wp.array | None = None  # (nstate,) float32, uploaded from _sign_host
        self._sign_host: np.ndarray | None = None

    def state(self, sign: np.ndarray) -> wp.array:
        """`(nworld, len(sign))` the first state columns, each times its sign, gathered now."""
        w, t = self._worlds, self._transfers
        with wp.ScopedDevice(w.device):
            if self._out is None:
                self._out = wp.zeros((w.nworld, len(sign)), dtype=wp.float32)
            if self._sign_host is None or not np.array_equal(self._sign_host, sign):
                self._sign_host = np.array(sign, np.float32)
                self._sign = wp.array(self._sign_host, dtype=wp.float32)
            out = self._out
            t.gather(t.state_dev, t.sensor_dev, t.time_dev)
            wp.launch(
                signed_columns,
                dim=out.shape,
                inputs=[t.state_dev, self._sign],
                outputs=[out],
                device=w.device,
            )
        return out

    def write(self, command: Any) -> None:
        """ctrl[:, the commands' actuators] = `command` (any DLPack array on the device, float32 or
        float64), and the kept copy of ctrl; parked worlds' ctrl stays zero."""
        w, t = self._worlds, self._transfers
        with wp.ScopedDevice(w.device):
            source = command if isinstance(command, wp.array) else wp.from_dlpack(command)
            if source.device != w.device:
                raise ValueError(f"command is on {source.device}, the worlds on {w.device}: put it there first")
            if source.dtype not in (wp.float32, wp.float64):
                raise ValueError(f"command must be float32 or float64, got {source.dtype.__name__}")
            wp.launch(
                command_to_ctrl,
                dim=source.shape,
                inputs=[source, t.actuator, w.parked],
                outputs=[t.ctrl_dev, w.d.ctrl],
                device=w.device,
            )
