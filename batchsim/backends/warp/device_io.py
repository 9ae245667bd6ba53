"""The device path on MuJoCo Warp (batchsim.device_io): the state gathered and signed into a
float32 device buffer, commands written into the simulation's ctrl, by kernels; no host copy."""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp


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


class WarpDeviceIO:
    """Mixed into WarpSystem: `_device_state` and `_write_device`."""

    _device_buffers: tuple[Any, Any] | None = None  # (state out, signs)

    def _buffers(self) -> tuple[Any, Any]:
        if self._device_buffers is None:
            state = self.spec.state
            with wp.ScopedDevice(self.device):
                self._device_buffers = (
                    wp.zeros((self.nworld, len(state)), dtype=wp.float32),
                    wp.array(np.array([c.sign for c in state], np.float32), dtype=wp.float32),
                )
        return self._device_buffers

    def _device_state(self) -> wp.array:
        out, sign = self._buffers()
        with wp.ScopedDevice(self.device):
            self._gather_on_device(self._state_dev, self._sensor_dev, self._time_dev)
            wp.launch(
                signed_columns,
                dim=out.shape,
                inputs=[self._state_dev, sign],
                outputs=[out],
                device=self.device,
            )
        return out

    def _write_device(self, command: Any) -> None:
        with wp.ScopedDevice(self.device):
            source = command if isinstance(command, wp.array) else wp.from_dlpack(command)
            if source.device != self.device:
                raise ValueError(
                    f"command is on {source.device}, the worlds on {self.device}: put it there first"
                )
            if source.dtype not in (wp.float32, wp.float64):
                raise ValueError(f"command must be float32 or float64, got {source.dtype.__name__}")
            wp.launch(
                command_to_ctrl,
                dim=source.shape,
                inputs=[source, self._actuator_dev, self._parked_dev],
                outputs=[self._ctrl_dev, self._d.ctrl],
                device=self.device,
            )
        self._ctrl_behind = self._cuda  # the host's ctrl lags the kept copy (the CPU device wrote it)
