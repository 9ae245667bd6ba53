"""Resetting worlds on MuJoCo Warp: `mjw.reset_data` on a mask, then the initial state's rows.

MuJoCo Warp's `reset_data` defines its kernels inside the function, so every call hashes
them again in Python: on an H100, resetting 819 of 8192 humanoids took 12-15 ms, most of it
that. The reset is captured in a graph once (beside the periods' graphs, dropped with them
when the buffers grow) and replayed: the mask is the only thing that changes, written into
the same device array before each replay. The first reset runs uncaptured: it loads the
kernels' modules, which a capture must not do. On a CUDA device only: `reset_data` allocates
temporaries, which a graph on Warp's CPU device cannot free afterwards (the process aborts).
"""

from __future__ import annotations

from typing import Any

import mujoco_warp as mjw
import numpy as np
import warp as wp

from batchsim.backends.warp.kernels import set_clock, set_rows

RESET = "reset"  # its key among the system's graphs


class WarpReset:
    """Mixed into WarpSystem: `_reset_on_device`."""

    _graphs: dict[Any, Any]
    _reset_loaded = False  # whether the reset's kernels have run once (modules loaded)

    def _reset_on_device(self, worlds: np.ndarray | None) -> None:
        mask = np.ones(self.nworld, bool) if worlds is None else np.isin(np.arange(self.nworld), worlds)
        with wp.ScopedDevice(self.device):
            self._mask_dev.assign(mask)
            if not (self._cuda and self.options["graph"] and self._reset_loaded):
                self._reset_kernels()
                self._reset_loaded = True
            else:
                graph = self._graphs.get(RESET)
                if graph is None:
                    with wp.ScopedCapture(device=self.device) as capture:
                        self._reset_kernels()
                    graph = self._graphs[RESET] = capture.graph
                wp.capture_launch(graph)
            self._parked_dev.assign(self.frozen.astype(np.int32))

    def _reset_kernels(self) -> None:
        """The masked worlds to MuJoCo's defaults, then the initial state and mj_forward's
        qfrc_actuator and sensordata of it (as on cpu), and their clocks."""
        d = self._d
        mjw.reset_data(self._m, d, reset=self._mask_dev)
        for field, row in self._initial_rows.items():
            wp.launch(
                set_rows,
                dim=(self.nworld, row.shape[0]),
                inputs=[self._mask_dev, row],
                outputs=[getattr(d, field)],
                device=self.device,
            )
        wp.launch(
            set_clock,
            dim=self.nworld,
            inputs=[self._mask_dev, self._time0],
            outputs=[self._clock, d.time],
            device=self.device,
        )
