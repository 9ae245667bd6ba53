"""The arrays a fleet over several devices shares with its shards (batchsim/backends/sharded/system.py,
shards.py), and one shard's rows of them: local memory when the shards are threads, a
shared-memory segment when they are processes.

    layout = fleet_layout(nworld, ncolumn, nsensordata, ncommand, nbody, nshard)
    rows = FleetRows(memory, range(0, 4096))   # shard 0's rows
    rows.share(system)                         # its system reads into them: no copy
"""

from __future__ import annotations

from typing import Any

from batchsim.backends.sharded.messages import control_array
from batchsim.memory import Layout, Memory


def fleet_layout(
    nworld: int, ncolumn: int, nsensordata: int, ncommand: int, nbody: int = 1, nshard: int = 1
) -> Layout:
    """The fleet's arrays that its shards read from or write to: readings `(nworld, ncolumn)`
    (state, then base_state, then what the shards' actuation reads), sensordata `(nworld,
    nsensordata)`, time, status and command `(nworld, ncommand)`; every world's body poses,
    xpos `(nworld, nbody, 3)` and xquat `(nworld, nbody, 4)` (their pages taken only once
    asked for); and each shard process's control row (shard_messages)."""
    return Layout(
        [
            ("readings", (nworld, ncolumn), "f8"),
            ("sensordata", (nworld, nsensordata), "f8"),
            ("time", (nworld,), "f8"),
            ("status", (nworld,), "u1"),
            ("command", (nworld, ncommand), "f8"),
            ("xpos", (nworld, nbody, 3), "f8"),
            ("xquat", (nworld, nbody, 4), "f8"),
            control_array(nshard),
        ]
    )


class FleetRows:
    """One shard's rows of the fleet's arrays, and the copies between them and its system.

    A shard's system reads its readings into these rows and takes its commands from them
    (`share`, BatchedSystem.share_host_arrays): those copies are then none. The
    8192 humanoids of one GPU read 9.1 MB a period, whose copy took a shard process 0.7 ms
    of its 0.87 ms read (4 H200s, benchmarks/RESULTS.md, GPU session 4)."""

    def __init__(self, memory: Memory, rows: range):
        sel = slice(rows.start, rows.stop)
        self.readings = memory["readings"][sel]
        self.sensordata = memory["sensordata"][sel]
        self.time = memory["time"][sel]
        self.status = memory["status"][sel]
        self.command = memory["command"][sel]
        self.xpos = memory["xpos"][sel]
        self.xquat = memory["xquat"][sel]

    def share(self, system: Any) -> None:
        """Make these rows `system`'s own readings, sensordata and command (before configure)."""
        system.share_host_arrays(self.readings, self.sensordata, self.command)

    def take_command(self, system: Any) -> None:
        if system.command is not self.command:
            system.command[:] = self.command

    def give_status(self, system: Any) -> None:
        self.status[:] = system.status

    def give_readings(self, system: Any) -> None:
        # whole blocks, one copy each (the same robot: the same columns on both sides)
        if system.readings is not self.readings:
            self.readings[:] = system.readings
            self.sensordata[:] = system.sensordata.array
        self.time[:] = system.time
        self.status[:] = system.status

    def give_command(self, system: Any) -> None:
        if system.command is not self.command:
            self.command[:] = system.command

    def give_poses(self, system: Any) -> None:
        """Every world's body poses (as system.body_poses() gives them) into these rows."""
        system.body_poses_into(self.xpos, self.xquat)
