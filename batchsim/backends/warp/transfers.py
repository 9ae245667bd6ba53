"""A control period's transfers on MuJoCo Warp: write()'s commands to the device and read()'s
gather of the state into the host arrays.

Commands that are plain copies into actuators (no PIDs, scaling, mimic joints or
transmissions) go up as they are: `command` is pinned memory, copied to the device whole,
where one kernel checks each world's row (NaN, inf, beyond MAX_COMMAND) and narrows the good
rows into ctrl; the rejected rows come back, one flag a world, and write() waits for them.
The host makes no pass over the commands: on the GPU hosts the two reductions of its check
and the narrowing took 0.16-0.29 ms of a 15 ms period of 8192 humanoids (period_profile.py).
Other commands are turned into ctrl on the host (batchsim.actuation), which then goes up as
float32.

Each is a few Warp calls (a copy, a kernel launch; a kernel launch and three copies), and on
an H100 host each call costs 30-90 us of Python (the arguments packed, the device scoped),
which added up to ~0.7 ms of a 16 ms period of 8192 humanoids (benchmarks/period_profile.py).
On a CUDA device they are captured once in a graph each (beside the periods' graphs, under
keys WRITE and READ, dropped with them when the buffers grow) and replayed: one launch each.
The first call runs uncaptured, so that the kernels' modules are loaded before a capture.
Warp's CPU device launches them one by one (its graphs replay no faster).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import warp as wp

from batchsim.backends.warp.kernels import apply_commands, gather_state, narrow_ctrl
from batchsim.types import MAX_COMMAND

WRITE, READ, COMMANDS = "write", "read", "commands"  # their keys among the system's graphs


class WarpTransfers:
    """Mixed into WarpSystem: `_apply_commands`, `_ctrl_host`, `_upload_ctrl`, `_read`,
    `_gather_on_device`."""

    _graphs: dict[Any, Any]
    _ctrl_behind = False  # whether the host's ctrl lags the device's kept copy (after _apply_commands)

    def _apply_commands(self) -> Any:
        if not self._command.size:  # type: ignore[attr-defined]
            return None
        if not self._replay_captured(COMMANDS):
            with wp.ScopedDevice(self.device):  # type: ignore[attr-defined]
                self._replay(COMMANDS, self._command_kernels)
        wp.synchronize_device(self.device)  # type: ignore[attr-defined]
        self._ctrl_behind = self._cuda  # type: ignore[attr-defined]  # (the CPU device writes the host's)
        return self._rejected

    def _command_kernels(self) -> None:
        if self._cuda:  # type: ignore[attr-defined]
            wp.copy(self._command_dev, self._command_wp)  # type: ignore[attr-defined]
        wp.launch(
            apply_commands,
            dim=self.nworld,  # type: ignore[attr-defined]
            inputs=[self._command_dev, self._actuator_dev, self._parked_dev, float(MAX_COMMAND)],  # type: ignore[attr-defined]
            outputs=[self._ctrl_dev, self._d.ctrl, self._rejected_dev],  # type: ignore[attr-defined]
            device=self.device,  # type: ignore[attr-defined]
        )
        if self._cuda:  # type: ignore[attr-defined]
            wp.copy(self._rejected_wp, self._rejected_dev)  # type: ignore[attr-defined]

    def _ctrl_host(self) -> Any:
        if self._ctrl_behind:  # the commands went up whole: bring the kept ctrl down (a reset's, a park's)
            with wp.ScopedDevice(self.device):  # type: ignore[attr-defined]
                wp.copy(self._ctrl_wp, self._ctrl_dev)  # type: ignore[attr-defined]
                wp.synchronize_device(self.device)  # type: ignore[attr-defined]
            self._ctrl_behind = False
        return self._ctrl  # type: ignore[attr-defined]

    def _upload_ctrl(self) -> None:
        self._ctrl_host()  # up to date first: all of it goes up
        if self._replay_captured(WRITE):
            return
        with wp.ScopedDevice(self.device):  # type: ignore[attr-defined]
            self._replay(WRITE, self._upload_kernels)

    def _upload_kernels(self) -> None:
        if self._cuda:  # type: ignore[attr-defined]
            wp.copy(self._ctrl_dev, self._ctrl_wp)  # type: ignore[attr-defined]
        wp.launch(  # the device named: ScopedDevice is process-wide, and shards write at once
            narrow_ctrl,
            dim=self._ctrl.shape,  # type: ignore[attr-defined]
            inputs=[self._ctrl_dev, self._parked_dev],  # type: ignore[attr-defined]
            outputs=[self._d.ctrl],  # type: ignore[attr-defined]
            device=self.device,  # type: ignore[attr-defined]
        )

    def _read(self) -> None:
        if not self._replay_captured(READ):
            with wp.ScopedDevice(self.device):  # type: ignore[attr-defined]
                self._replay(READ, self._read_kernels)
        wp.synchronize_device(self.device)  # type: ignore[attr-defined]

    def _read_kernels(self) -> None:
        self._gather_on_device(self._state_dev, self._sensor_dev, self._time_dev)  # type: ignore[attr-defined]
        if self._cuda:  # type: ignore[attr-defined]
            wp.copy(self._state_wp, self._state_dev)  # type: ignore[attr-defined]
            if self._sensor_host.size:  # type: ignore[attr-defined]
                wp.copy(self._sensor_wp, self._sensor_dev)  # type: ignore[attr-defined]
            wp.copy(self._time_wp, self._time_dev)  # type: ignore[attr-defined]

    def _replay_captured(self, key: Any) -> bool:
        """Launch the graph captured under `key`, if there is one: True. A graph names its
        device and stream, so no ScopedDevice is entered (~10 us each, three a period)."""
        graph = self._graphs.get(key) if self._cuda else None  # type: ignore[attr-defined]
        if graph is None:
            return False
        wp.capture_launch(graph)
        return True

    def _replay(self, key: str, kernels: Callable[[], None]) -> None:
        """`kernels()` as a graph replayed (CUDA, graphs on), else called."""
        if not (self._cuda and self.options["graph"]):  # type: ignore[attr-defined]
            kernels()
            return
        graph = self._graphs.get(key)
        if graph is None:
            kernels()  # loads the modules: a capture must not
            with wp.ScopedCapture(device=self.device) as capture:  # type: ignore[attr-defined]
                kernels()
            graph = self._graphs[key] = capture.graph
        wp.capture_launch(graph)

    def _gather_on_device(self, state_out: wp.array, sensordata_out: wp.array, time_out: wp.array) -> None:
        d = self._d  # type: ignore[attr-defined]
        wp.launch(
            gather_state,
            dim=(self.nworld, self._ncols),  # type: ignore[attr-defined]
            inputs=[
                d.qpos,
                d.qvel,
                d.qfrc_actuator,
                d.sensordata,
                self._clock,  # type: ignore[attr-defined]
                self._source,  # type: ignore[attr-defined]
                self._index,  # type: ignore[attr-defined]
                self._readings.shape[1],  # type: ignore[attr-defined]
            ],
            outputs=[state_out, sensordata_out, time_out],
            device=self.device,  # type: ignore[attr-defined]  # named: a sharded fleet reads its shards at once
        )
