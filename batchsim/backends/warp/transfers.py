"""A control period's transfers on MuJoCo Warp: write()'s commands to the device and read()'s
gather of the state into the host arrays (`Transfers`: the device's side of the host arrays
and the kernels that move them; the engine replays them).

Commands that are plain copies into actuators (no PIDs, scaling, mimic joints or
transmissions) go up as they are: `command` is pinned memory, copied to the device whole,
where one kernel checks each world's row (NaN, inf, beyond MAX_COMMAND) and narrows the good
rows into ctrl; the rejected rows come back, one flag a world, and write() waits for them.
The host makes no pass over the commands: on the GPU hosts the two reductions of its check
and the narrowing took 0.16-0.29 ms of a 15 ms period of 8192 humanoids (period_profile.py).
Other commands are turned into ctrl on the host (batchsim.parts.actuation), which then goes up as
float32.

Each is a few Warp calls (a copy, a kernel launch; a kernel launch and three copies), and on
an H100 host each call costs 30-90 us of Python (the arguments packed, the device scoped),
which added up to ~0.7 ms of a 16 ms period of 8192 humanoids (benchmarks/period_profile.py).
On a CUDA device the engine captures each once in a graph (its Graphs, under the keys WRITE,
READ and COMMANDS, dropped with the periods' when the buffers grow) and replays it: one
launch each. The first call runs uncaptured, so that the kernels' modules are loaded before a
capture. Warp's CPU device launches them one by one (its graphs replay no faster).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from batchsim.backends.warp.host import HostArrays, host_array
from batchsim.backends.warp.kernels import apply_commands, gather_state, narrow_ctrl
from batchsim.backends.warp.worlds import DeviceWorlds
from batchsim.engine import EngineBuffers
from batchsim.types import MAX_COMMAND, READ_FIELDS

WRITE, READ, COMMANDS = "write", "read", "commands"  # their keys among the engine's graphs


class Transfers:
    """The device's side of the host arrays, and the kernels between them.

    Attributes:
      host: the host arrays (HostArrays) read() fills and commands come from.
      ctrl: (nworld, nu) float32 host ctrl (pinned on a GPU): what commands through PIDs,
        scaling, mimic joints or transmissions become on the host, and what resets and parks
        upload; ctrl_host its Warp array, ctrl_dev the device's kept copy of it.
      rejected: (nworld,) bool host array, the rows the device's check rejected.
      state_dev, sensor_dev, time_dev: the gather's device outputs (the host arrays
        themselves on Warp's CPU device).
      actuator: (ncommand,) int32, the actuator each command column drives.
    """

    def __init__(self, worlds: DeviceWorlds, host: HostArrays, buffers: EngineBuffers):
        w, n, cuda = worlds, worlds.nworld, worlds.cuda
        self._worlds = w
        self.host = host
        self.ctrl_host = host_array((n, w.model.nu), wp.float32, cuda)
        self.ctrl = self.ctrl_host.numpy()
        self._rejected_host = host_array((n,), wp.bool, cuda)
        self.rejected = self._rejected_host.numpy()
        self._ncolumn = buffers.readings.shape[1]
        self._ncols = self._ncolumn + buffers.sensordata.shape[1] + 1
        self._has_sensordata = bool(buffers.sensordata.size)
        source = np.zeros(self._ncolumn, np.int32)
        index = np.zeros(self._ncolumn, np.int32)
        for c, col in enumerate(buffers.columns):
            source[c], index[c] = READ_FIELDS.index(col.source.value), col.index
        self._source = wp.array(source, dtype=wp.int32)
        self._index = wp.array(index, dtype=wp.int32)
        self.actuator = wp.array(buffers.ctrl_index.astype(np.int32), dtype=wp.int32)
        if cuda:
            self.state_dev = wp.zeros(buffers.readings.shape, dtype=wp.float64)
            self.sensor_dev = wp.zeros(buffers.sensordata.shape, dtype=wp.float64)
            self.time_dev = wp.zeros(n, dtype=wp.float64)
            self.ctrl_dev = wp.zeros(self.ctrl.shape, dtype=wp.float32)
            self._command_dev = wp.zeros(buffers.command.shape, dtype=wp.float64)
            self._rejected_dev = wp.zeros(n, dtype=wp.bool)
        else:  # Warp's CPU device: the kernels read and write the host arrays themselves
            self.state_dev, self.sensor_dev, self.time_dev = host.readings, host.sensordata, host.time
            self.ctrl_dev = self.ctrl_host
            self._command_dev, self._rejected_dev = host.command, self._rejected_host
        # failed worlds' readings from the period's start, gathered apart from what read() shows
        self._failed = (
            wp.zeros(buffers.readings.shape, dtype=wp.float64),
            wp.zeros(buffers.sensordata.shape, dtype=wp.float64),
            wp.zeros(n, dtype=wp.float64),
        )

    # --- the programs the engine replays (under COMMANDS, WRITE and READ) ---
    def commands(self) -> None:
        """The commands up whole, checked and narrowed into ctrl; the rejected rows down."""
        w = self._worlds
        if w.cuda:
            wp.copy(self._command_dev, self.host.command)
        wp.launch(
            apply_commands,
            dim=w.nworld,
            inputs=[self._command_dev, self.actuator, w.parked, float(MAX_COMMAND)],
            outputs=[self.ctrl_dev, w.d.ctrl, self._rejected_dev],
            device=w.device,
        )
        if w.cuda:
            wp.copy(self._rejected_host, self._rejected_dev)

    def upload(self) -> None:
        """The host's ctrl up, into the simulation's (parked worlds zero)."""
        w = self._worlds
        if w.cuda:
            wp.copy(self.ctrl_dev, self.ctrl_host)
        wp.launch(  # the device named: ScopedDevice is process-wide, and shards write at once
            narrow_ctrl,
            dim=self.ctrl.shape,
            inputs=[self.ctrl_dev, w.parked],
            outputs=[w.d.ctrl],
            device=w.device,
        )

    def read(self) -> None:
        """Every world's readings, sensordata and time gathered, then down into the host arrays."""
        self.gather(self.state_dev, self.sensor_dev, self.time_dev)
        if self._worlds.cuda:
            host = self.host
            wp.copy(host.readings, self.state_dev)
            if self._has_sensordata:
                wp.copy(host.sensordata, self.sensor_dev)
            wp.copy(host.time, self.time_dev)

    # --- beside them ---
    def download_ctrl(self) -> None:
        """The device's kept ctrl (the commands' narrowing wrote it) into the host's."""
        wp.copy(self.ctrl_host, self.ctrl_dev)

    def gather(self, state_out: wp.array, sensordata_out: wp.array, time_out: wp.array) -> None:
        """The read() columns, sensordata and time of every world, float64, into these device arrays."""
        w = self._worlds
        d = w.d
        wp.launch(
            gather_state,
            dim=(w.nworld, self._ncols),
            inputs=[d.qpos, d.qvel, d.qfrc_actuator, d.sensordata, w.clock, self._source, self._index, self._ncolumn],
            outputs=[state_out, sensordata_out, time_out],
            device=w.device,  # named: a sharded fleet reads its shards at once
        )

    def gather_rows(self, worlds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The raw readings, sensordata and time of `worlds` as the Data holds them now, host copies."""
        self.gather(*self._failed)
        readings, sensordata, time = (a.numpy()[worlds] for a in self._failed)
        return readings, sensordata, time
