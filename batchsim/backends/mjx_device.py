"""The device path on MJX (batchsim.device_io): the state gathered and signed by a jitted
program, commands written into the Data's ctrl by another; no host copy."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


class MjxDeviceIO:
    """Mixed into MjxSystem: `_device_state` and `_write_device`."""

    _device_programs: tuple[Any, Any] | None = None  # (state, write)

    def _device_jits(self) -> tuple[Any, Any]:
        if self._device_programs is None:
            nstate = len(self.spec.state)
            sign = jnp.asarray(np.array([c.sign for c in self.spec.state], np.float32))
            actuator = jnp.asarray(np.array([c.actuator_id for c in self.spec.commands], np.int32))
            read = self._programs.read

            def state(qpos: jax.Array, qvel: jax.Array, qfrc: jax.Array, sensordata: jax.Array) -> jax.Array:
                return read(qpos, qvel, qfrc, sensordata)[:, :nstate] * sign

            def write(ctrl: jax.Array, command: jax.Array, parked: jax.Array) -> jax.Array:
                ctrl = ctrl.at[:, actuator].set(command.astype(ctrl.dtype))
                return jnp.where(parked[:, None], jnp.zeros_like(ctrl), ctrl)

            self._device_programs = (jax.jit(state), jax.jit(write))
        return self._device_programs

    def _device_state(self) -> jax.Array:
        d = self._d
        return self._device_jits()[0](d.qpos, d.qvel, d.qfrc_actuator, d.sensordata)

    def _write_device(self, command: Any) -> None:
        self._sync_inputs()  # what write() staged on the host goes up first, then the device's command over it
        source = command if isinstance(command, jax.Array) else jax.dlpack.from_dlpack(command)
        if source.dtype not in (jnp.float32, jnp.float64):
            raise ValueError(f"command must be float32 or float64, got {source.dtype}")
        parked = jax.device_put(self.frozen, self.device)
        self._d = self._d.replace(ctrl=self._device_jits()[1](self._d.ctrl, source, parked))
        self._ctrl_behind = True  # the host's ctrl, which resets upload whole, is brought down when wanted
        self._packed = None
