"""One control period on MuJoCo Warp (`Period`): its program (the period's start kept on the
device, the held base velocity, the `nstep` physics steps, the float64 clock and the per-world
check), captured in a graph once per `nstep` and launched with one call; the start restored
where the period must be repeated (grown buffers) or a failed world read as it was.

The check's flags (one failure code a world, batchsim.backends.device) come back to the host
inside the graph, into pinned memory: the period is one launch and one wait.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from batchsim.backends.warp.buffers import BUFFER_OVERFLOWS
from batchsim.backends.warp.host import host_array
from batchsim.backends.warp.kernels import (
    CPU_GRAPHS,
    advance_clock,
    check_worlds,
    copy_items,
    copy_rows,
    hold_base_velocity,
    rotate_base_velocity,
)
from batchsim.backends.warp.worlds import DeviceWorlds, Graphs
from batchsim.types import MAX_COMMAND, HeldBase

# what a period changes of MuJoCo's integration state (inputs such as ctrl and mocap it only
# reads), kept at its start
CHANGED = int(mjw.State.PHYSICS | mjw.State.WARMSTART)


class Period:
    """The control period of the engine's worlds.

    Attributes:
      flags: (nworld,) int32 host array, each world's failure code after the last launch (0: fine).
    """

    def __init__(self, worlds: DeviceWorlds, graphs: Graphs, dt: float, held_base: HeldBase | None):
        w, n = worlds, worlds.nworld
        self._worlds, self._graphs, self._dt = w, graphs, dt
        self._held_base = held_base
        self._flags_host = host_array((n,), wp.int32, w.cuda)
        self.flags = self._flags_host.numpy()
        self._flags_dev = wp.zeros(n, dtype=wp.int32) if w.cuda else self._flags_host
        # the period's start, kept on the device: to repeat it, or to read a failed world
        self._start = {
            "state": wp.zeros((n, mujoco.mj_stateSize(w.model, CHANGED)), dtype=wp.float32),
            "qfrc_actuator": wp.zeros_like(w.d.qfrc_actuator),
            "sensordata": wp.zeros_like(w.d.sensordata),
            "clock": wp.zeros_like(w.clock),
        }
        # the base velocity's target (batchsim.plugins.base_velocity): staged on the host, copied to the
        # device, rotated into the world at each period's start; NaN until write() stages one
        self._held_host = self._held_dev = self._held_world = None
        if held_base is not None:
            self._held_wp = host_array((n, 3), wp.float32, w.cuda)
            self._held_host = self._held_wp.numpy()
            self._held_host[:] = np.nan
            self._held_dev = wp.array(self._held_host, dtype=wp.float32) if w.cuda else self._held_wp
            self._held_world = wp.zeros((n, 3), dtype=wp.float32)

    def launch(self, nstep: int, meanwhile: Callable[[], None]) -> None:
        """Run one period of `nstep` steps, `meanwhile()` between its launch and the wait."""
        graphs = self._graphs
        if graphs.replay(nstep):  # the flags' copy to the host is in it
            meanwhile()
            wp.synchronize_device(graphs.device)
            return
        serial = CPU_GRAPHS if graphs.enabled and not graphs.cuda else contextlib.nullcontext()
        with wp.ScopedDevice(graphs.device), serial:
            if graphs.enabled:
                graph = graphs.get(nstep)
                if graph is None:
                    graph = graphs.capture(nstep, lambda: self._captured(nstep))
                wp.capture_launch(graph)  # the flags' copy to the host is in it
            else:
                self._program(nstep)
                if graphs.cuda:
                    wp.copy(self._flags_host, self._flags_dev)
            meanwhile()
            wp.synchronize_device(graphs.device)

    def _captured(self, nstep: int) -> None:
        self._program(nstep)
        if self._graphs.cuda:  # one call fewer a period: the check's flags come back inside the graph
            wp.copy(self._flags_host, self._flags_dev)

    def _program(self, nstep: int) -> None:
        w = self._worlds
        m, d = w.m, w.d
        self.keep_start()
        drive = self._held_base
        if drive is not None:
            inputs = [d.qpos, self._held_dev, drive.qposadr]
            wp.launch(rotate_base_velocity, dim=w.nworld, inputs=inputs, outputs=[self._held_world])
        for _ in range(nstep):
            if drive is not None:  # before every substep, as upstream's simulation applies it
                wp.launch(hold_base_velocity, dim=w.nworld, inputs=[self._held_world, drive.dofadr], outputs=[d.qvel])
            mjw.step(m, d)
        wp.launch(advance_clock, dim=w.nworld, inputs=[self._dt, nstep], outputs=[w.clock, d.time])
        wp.launch(
            check_worlds,
            dim=w.nworld,
            inputs=[d.qpos, d.qvel, d.qacc, d.overflow, BUFFER_OVERFLOWS, float(MAX_COMMAND)],
            outputs=[self._flags_dev],
        )

    def stage_base_velocity(self, target: np.ndarray) -> None:
        """The base velocity's target `(nworld, 3)`, held from the next period on."""
        np.copyto(self._held_host, target, casting="same_kind")
        if self._worlds.cuda:  # pinned memory: the copy is queued ahead of the next period's graph
            with wp.ScopedDevice(self._worlds.device):
                wp.copy(self._held_dev, self._held_wp)

    # --- the period's start: kept, restored ---
    def keep_start(self) -> None:
        """Copy what a period changes (mjSTATE_PHYSICS, the warmstart, and the derived fields
        read() gathers) of every world, on the device."""
        w, start = self._worlds, self._start
        d = w.d
        mjw.get_state(w.m, d, start["state"], CHANGED)
        wp.copy(start["qfrc_actuator"], d.qfrc_actuator)
        if d.sensordata.size:
            wp.copy(start["sensordata"], d.sensordata)
        wp.copy(start["clock"], w.clock)

    def restore_start(self, mask: Any) -> None:
        """Put the masked worlds (a (nworld,) bool device array; None: all) back where the
        period started."""
        w, start = self._worlds, self._start
        d = w.d
        mjw.set_state(w.m, d, start["state"], CHANGED, active=mask)
        if mask is None:
            wp.copy(d.qfrc_actuator, start["qfrc_actuator"])
            if d.sensordata.size:
                wp.copy(d.sensordata, start["sensordata"])
            wp.copy(w.clock, start["clock"])
            return
        for field in ("qfrc_actuator", "sensordata"):
            out = getattr(d, field)
            if out.size:
                wp.launch(copy_rows, dim=out.shape, inputs=[mask, start[field]], outputs=[out])
        wp.launch(copy_items, dim=w.nworld, inputs=[mask, start["clock"]], outputs=[w.clock])
