"""The state and the commands on the engine's own device, for users who stay there (a policy
on the GPU): `device_state()` and `write_device(command)`, beside the host's `state` and
`command`. Mixed into BatchedSystem; the engine hooks are `_device_state` and `_write_device`.

A control period then moves no state through the host: `write_device(actions)`, `step(n)`,
`device_state()`. What still comes back per period is what step() always reads, one failure
code per world. The arrays are the backend's own (warp: `wp.array`, mjx: `jax.Array`, cpu:
host NumPy), float32 on the GPU backends, and speak DLPack (`torch.from_dlpack(a)`,
`jax.dlpack.from_dlpack(a)`).
"""

from __future__ import annotations

from typing import Any

from batchsim.lifecycle import LifecycleState
from batchsim.types import ConfigurationError

_RUNNING = frozenset({LifecycleState.INACTIVE, LifecycleState.ACTIVE})


class DeviceIO:
    """The device-side reads and writes of the contract (batchsim.hardware)."""

    def device_state(self) -> Any:
        """`(nworld, nstate)` the state interfaces, gathered now on the engine's device, signed as
        `state` is (`export_state_interfaces()` order), without sensor noise; rows of frozen
        worlds are parked and meaningless until reset. warp reuses one buffer: the next call
        overwrites it.

        Raises:
          ConfigurationError: interfaces that pass through transmissions (computed on the host).
        """
        self._require("read the device state", _RUNNING)  # type: ignore[attr-defined]
        if self.spec.transmissions:  # type: ignore[attr-defined]
            raise ConfigurationError(
                "device_state(): the transmissions' joint interfaces are computed on the host: use read() and state"
            )
        return self._device_state()

    def write_device(self, command: Any) -> None:
        """Apply `command` `(nworld, ncommand)` (any DLPack array, float32 or float64, on the
        engine's device) to every world's ctrl on the device, as write() applies `self.command`;
        parked (frozen) worlds keep a zero ctrl. No BAD_COMMAND check (the values never reach
        the host): a NaN reaches MuJoCo, which diverges that world, frozen as always. ACTIVE only.

        Raises:
          ConfigurationError: commands that do not map one to one onto actuators (PIDs, scaled
            grippers, mimic joints, transmissions: they run on the host; use command and write()).
        """
        self._require("write commands on the device", frozenset({LifecycleState.ACTIVE}))  # type: ignore[attr-defined]
        if not self._actuation.trivial:  # type: ignore[attr-defined]
            raise ConfigurationError(
                "write_device(): these command interfaces are not plain copies into actuators "
                "(PIDs, scaling, mimic joints or transmissions run on the host): use command and write()"
            )
        shape = tuple(getattr(command, "shape", ()))
        want = (self.nworld, len(self.spec.commands))  # type: ignore[attr-defined]
        if shape != want:
            raise ValueError(f"command must have shape {want}, got {shape}")
        self._write_device(command)

    # --- the engine hooks ---
    def _device_state(self) -> Any:
        """The backend's `(nworld, nstate)` signed state interfaces on its device (device_state())."""
        raise NotImplementedError(f"the {self.name} backend has no device arrays")  # type: ignore[attr-defined]

    def _write_device(self, command: Any) -> None:
        """ctrl[:, the command's actuators] = `command` on the device, parked worlds zero (write_device())."""
        raise NotImplementedError(f"the {self.name} backend has no device arrays")  # type: ignore[attr-defined]
