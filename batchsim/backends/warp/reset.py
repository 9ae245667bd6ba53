"""Resetting worlds on MuJoCo Warp (`Reset`): `mjw.reset_data` on a mask, then the initial
state's rows.

MuJoCo Warp's `reset_data` defines its kernels inside the function, so every call hashes
them again in Python: on an H100, resetting 819 of 8192 humanoids took 12-15 ms, most of it
that. The reset is captured in a graph once (among the engine's graphs, dropped with them
when the buffers grow) and replayed: the mask is the only thing that changes, written into
the same device array before each replay. The first reset runs uncaptured: it loads the
kernels' modules, which a capture must not do. On a CUDA device only: `reset_data` allocates
temporaries, which a graph on Warp's CPU device cannot free afterwards (the process aborts).
"""

from __future__ import annotations

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from batchsim.backends.warp.kernels import set_clock, set_rows
from batchsim.backends.warp.worlds import DeviceWorlds, Graphs

RESET = "reset"  # its key among the engine's graphs

# what a reset world is set to beyond reset_data's defaults: the initial state (a keyframe,
# initial values) and mj_forward's derived fields of it
_INITIAL_FIELDS = (
    ("qpos", wp.float32),
    ("qvel", wp.float32),
    ("act", wp.float32),
    ("ctrl", wp.float32),
    ("qfrc_actuator", wp.float32),
    ("sensordata", wp.float32),
    ("mocap_pos", wp.vec3),
    ("mocap_quat", wp.quat),
    ("xpos", wp.vec3),  # body poses of the initial state, as cpu's reset computes them
    ("xquat", wp.quat),
)


class Reset:
    """Puts worlds at the initial state `mjd` (an MjData, mj_forward run), on the device."""

    def __init__(self, worlds: DeviceWorlds, graphs: Graphs, mjd: mujoco.MjData):
        self._worlds, self._graphs = worlds, graphs
        self._time0 = float(mjd.time)
        self._rows = {
            field: wp.array(np.asarray(getattr(mjd, field), np.float32), dtype=dtype)
            for field, dtype in _INITIAL_FIELDS
            if getattr(mjd, field).size
        }
        self._loaded = False  # whether the reset's kernels have run once (modules loaded)

    def __call__(self, worlds: np.ndarray | None, frozen: np.ndarray) -> None:
        """Reset `worlds` (None: all); park the `frozen` ones ((nworld,) bool), unpark the others."""
        w = self._worlds
        mask = np.ones(w.nworld, bool) if worlds is None else np.isin(np.arange(w.nworld), worlds)
        with wp.ScopedDevice(w.device):
            w.mask.assign(mask)
            graphs = self._graphs
            if not (w.cuda and graphs.enabled and self._loaded):
                self._program()
                self._loaded = True
            else:
                graph = graphs.get(RESET)
                if graph is None:
                    graph = graphs.capture(RESET, self._program)
                wp.capture_launch(graph)
            w.parked.assign(frozen.astype(np.int32))

    def _program(self) -> None:
        """The masked worlds to MuJoCo's defaults, then the initial state and mj_forward's
        qfrc_actuator and sensordata of it (as on cpu), and their clocks."""
        w = self._worlds
        d = w.d
        mjw.reset_data(w.m, d, reset=w.mask)
        for field, row in self._rows.items():
            wp.launch(
                set_rows,
                dim=(w.nworld, row.shape[0]),
                inputs=[w.mask, row],
                outputs=[getattr(d, field)],
                device=w.device,
            )
        wp.launch(
            set_clock,
            dim=w.nworld,
            inputs=[w.mask, self._time0],
            outputs=[w.clock, d.time],
            device=w.device,
        )
