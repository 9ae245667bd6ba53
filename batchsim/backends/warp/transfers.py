"""A control period's transfers on MuJoCo Warp: write()'s upload of the commands and read()'s
gather of the state into the host arrays.

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

from batchsim.backends.warp.kernels import gather_state, narrow_ctrl

WRITE, READ = "write", "read"  # their keys among the system's graphs


class WarpTransfers:
    """Mixed into WarpSystem: `_upload_ctrl`, `_read`, `_gather_on_device`."""

    _graphs: dict[Any, Any]

    def _upload_ctrl(self) -> None:
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
