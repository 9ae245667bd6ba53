"""The `warp` backend: MuJoCo Warp (`mujoco_warp`) in float32, on an NVIDIA GPU or Warp's CPU device.

One control period is one captured graph: the `nstep` physics steps, the float64 clock and
a per-world check kernel, captured once per `nstep` and launched with one call (Warp replays
graphs on its CPU device too). Commands go up and state comes down once per period
(`write`, `read`), through pinned host buffers allocated once, when the contract binds them; nothing crosses
the bus per physics step.

Failures are data, as in MuJoCo Warp itself: a world whose qpos, qvel or qacc goes
non-finite or beyond MuJoCo's mjMAXVAL gets DIVERGED. Such a world is frozen: it reads as it
did before the step() in which it failed, while on the device it is parked (reset, ctrl
held at zero) so that it costs the others nothing, until `reset()` lists it.

Buffers grow instead of freezing the fleet. Contact and constraint buffers (`nconmax` per
world on average, pooled over the worlds as MuJoCo Warp does, and `njmax` per world) start
at the size a short CPU rollout of the model suggests, with headroom (or the options'). Each
period starts by keeping a device-side copy of every world's integration state; when a
period overflows one of them, the buffers are re-allocated larger (at least twice, more
where MuJoCo Warp's counters say so), the state carried over, the graphs re-captured and the
period run again from its start, so that its result is as if the buffers had been big
enough; one log line says what grew and to what. Only what cannot grow freezes worlds with
OVERFLOW: the device's free memory (or `max_data_bytes`), or a limit of the model itself
(height-field contacts per pair, tactile pairs, the EPA horizon).

Time is float64: a device-side float64 clock per world, advanced in the graph one addition
per step as mj_step adds them, copied into MuJoCo Warp's float32 `d.time` each period.

`device_arrays()` hands out the live Warp arrays (zero copy, DLPack-capable) for users
who stay on the device.

Modules, one job each:
  engine.py     WarpEngine: the Engine's calls, conducted over the helpers it owns; failures
                gathered, buffers grown
  worlds.py     DeviceWorlds (Model, Data and per-world arrays, shared by the helpers) and Graphs
  host.py       the pinned host arrays (bind), and page-locking a fleet's shared memory
  transfers.py  Transfers: write()'s commands up and read()'s gather down, graphed
  period.py     Period: a control period's program and graph, its start kept and restored
  reset.py      Reset: worlds back to the initial state, graphed
  poses.py      Poses: body poses for the host
  wrench.py     Wrenches: external wrenches staged for the next period
  device_io.py  DeviceIO: the device path (device_state, write_device)
  fields.py     per-world model fields in MuJoCo Warp's batched model arrays
  sensors.py    Sensors: cameras and lidars, MuJoCo Warp's rendering and ray casting, graphed
  kernels.py    the Warp kernels of a control period (checks, ctrl, gathers, clock, resets)
  buffers.py    buffer sizing from a CPU rollout, the overflow tables, growth and its memory
"""

from __future__ import annotations

import warp as wp

# Before anything imports mujoco_warp (every module of this package is imported after this
# file has run): no banner on stdout, where `batchsim info` and the CLI print, and no
# "Module ... load on device" line per kernel.
wp.config.quiet = True
if wp.config.log_level <= wp.LOG_INFO:
    wp.config.log_level = wp.LOG_WARNING

from batchsim.backends.warp.buffers import rollout_sizes  # noqa: E402
from batchsim.backends.warp.engine import WarpEngine  # noqa: E402

__all__ = ["WarpEngine", "rollout_sizes"]
