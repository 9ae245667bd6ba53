"""What the shipped backends' physics take in memory, measured: each one's `physics_memory`
(batchsim.startup.PhysicsMemory; batchsim.startup adds the contract's host arrays, the ROS 2
bridge and the controllers to it).

Measured 2026-11-21 on the 2-core development machine, MuJoCo 4, as RSS deltas between two
fleet sizes of one process unless said otherwise.
"""

from __future__ import annotations

import os

import mujoco

from batchsim.startup import PhysicsMemory, mjdata_bytes

# cpu: mujoco.batch's per-thread MjData: 0.25 MB per thread measured for the humanoid (256
# worlds, 16 threads vs 1) of its 14.7 MB arena; narena / 32 covers it. Its state rows are the
# contract's host arrays themselves (batchsim.startup.HOST_ROW_FACTOR was measured on it).
THREAD_ARENA_FRACTION = 1 / 32

# warp: MuJoCo Warp's Data per world, summed over its arrays (put_data at 100 vs 200
# worlds, the rollout-sized nconmax/njmax): 0.52x (arm), 0.58x (quadruped), 0.60x
# (humanoid) of MjData's own arrays; doubling nconmax and njmax added ~12 B per row.
WARP_DATA_FACTOR = 0.65
WARP_BYTES_PER_ROW = 12  # per contact (nconmax) and per constraint row (njmax), per world
# when nconmax / njmax are not known yet (the rollout-sized values come later): per world
WARP_DEFAULT_NCONMAX, WARP_DEFAULT_NJMAX = 4, 64

# mjx: MJX's Data per world (mjx.put_data's leaves): 0.46x (arm), 4.35x (quadruped: a
# contact slot for every candidate geom pair), 1.97x (humanoid) of MjData's arrays.
# XLA's temporaries while stepping are not included.
MJX_DATA_FACTOR = 4.4


def cpu(m: mujoco.MjModel, *, nthread: int | None = None, **_: int | None) -> PhysicsMemory:
    """mujoco.batch: nothing per world beside the host arrays (they are its rows); a scratch
    MjData's share per thread (`nthread` None: every core)."""
    return PhysicsMemory(0, int((nthread or os.cpu_count() or 1) * m.narena * THREAD_ARENA_FRACTION))


def warp(m: mujoco.MjModel, *, nconmax: int | None = None, njmax: int | None = None, **_: int | None) -> PhysicsMemory:
    """MuJoCo Warp's Data per world, with `nconmax` contacts and `njmax` constraint rows."""
    rows = nconmax if nconmax is not None else WARP_DEFAULT_NCONMAX
    rows += njmax if njmax is not None else WARP_DEFAULT_NJMAX
    return PhysicsMemory(int(WARP_DATA_FACTOR * mjdata_bytes(m)) + WARP_BYTES_PER_ROW * rows)


def mjx(m: mujoco.MjModel, **_: int | None) -> PhysicsMemory:
    """MJX's Data per world."""
    return PhysicsMemory(int(MJX_DATA_FACTOR * mjdata_bytes(m)))
