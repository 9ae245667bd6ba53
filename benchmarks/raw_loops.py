"""The raw libraries' own loops that benchmarks time the contract against, NSTEP physics steps
a call, each on its own engine data built from a batchsim fleet's model, size and buffers:

  cpu   mujoco.batch.Batch: ctrl[:] = u; batch.step(nstep=NSTEP)
  mjx   jax.jit(lax.scan over NSTEP of jax.vmap(mjx.step)), Data donated, float32 products
  warp  MuJoCo Warp: NSTEP mjw.step captured in one graph, launched and synchronized; with
        `keep_start` and `io`, also what batchsim's period copies and moves (the floor)

and whether a warp comparison stepped the same physics (`unequal_buffers`). Used by
throughput.py, period_profile.py, devices.py and mjx_period.py.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled

import batchsim  # noqa: E402

NSTEP = 10  # physics steps a call (a control period's worth), on every side
# whether the raw loop writes its commands every call (cpu: `ctrl[:] = u`) or sets them once (mjx,
# warp: on the device before the loop): the contract's loop does the same user work beside it
COPIES_EACH_CALL = {"cpu": True, "mjx": False, "warp": False}


def raw_cpu(sim: batchsim.BatchedSystem, ctrl: np.ndarray) -> Callable[[], None]:
    from mujoco import batch as mjbatch

    batch = mjbatch.Batch(sim.model, sim.nworld, nthread=sim.nthread)
    batch.reset()
    bound = batch.bind("ctrl")

    def body() -> None:
        bound[:] = ctrl
        batch.step(nstep=NSTEP)

    body.keep = batch  # type: ignore[attr-defined]
    body()  # one period, as the other raw loops spend compiling
    return body


def mjx_rollout(sim: batchsim.BatchedSystem, ctrl: np.ndarray) -> tuple[Callable[..., Any], Any]:
    """The raw MJX loop: a jitted lax.scan over NSTEP of vmap(mjx.step), Data donated, and a
    fresh Data for `sim`'s model and size with `ctrl` set. Call it under
    jax.default_matmul_precision("highest") to match batchsim's float32 products."""
    import jax
    import jax.numpy as jnp
    import mujoco
    from mujoco import mjx

    m = sim.model
    mx = mjx.put_model(m, device=sim.device, impl="jax")
    mjd = mujoco.MjData(m)
    mujoco.mj_forward(m, mjd)
    d0 = mjx.put_data(m, mjd, device=sim.device, impl="jax")
    d = jax.tree.map(lambda x: jnp.repeat(x[None], sim.nworld, axis=0), d0)
    d = d.replace(ctrl=jax.device_put(ctrl.astype(np.float32), sim.device))
    step = jax.vmap(mjx.step, in_axes=(None, 0))

    def scan(d):
        return jax.lax.scan(lambda d, _: (step(mx, d), None), d, None, length=NSTEP)[0]

    options = None
    if sim.options["deterministic"] and sim.device.platform == "gpu":
        options = {"xla_gpu_deterministic_ops": True}  # as the contract compiles
    return jax.jit(scan, donate_argnums=0, compiler_options=options), d


def raw_mjx(sim: batchsim.BatchedSystem, ctrl: np.ndarray) -> Callable[[], None]:
    import jax

    rollout, d = mjx_rollout(sim, ctrl)
    state = {"d": d}

    def body() -> None:
        with jax.default_matmul_precision("highest"):  # float32 products, as batchsim's mjx runs
            state["d"] = rollout(state["d"])
        jax.block_until_ready(state["d"].qpos)

    body()  # compile
    return body


def raw_warp(
    sim: batchsim.BatchedSystem, ctrl: np.ndarray, keep_start: bool = False, io: bool = False
) -> Callable[[], None]:
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    m = sim.model
    mjd = mujoco.MjData(m)
    mujoco.mj_forward(m, mjd)
    with wp.ScopedDevice(sim.device):
        mw = mjw.put_model(m)
        mw.opt.warn_overflow = 0
        if sim.options["deterministic"]:
            mw.opt.deterministic = int(mjw.DeterminismType.ALL)  # as the contract sets it
        d = mjw.put_data(m, mjd, nworld=sim.nworld, nconmax=sim.nconmax, njmax=sim.njmax)
        d.ctrl.assign(ctrl.astype(np.float32))
        sig = int(mjw.State.PHYSICS | mjw.State.WARMSTART)
        start = (
            wp.zeros((sim.nworld, mujoco.mj_stateSize(m, sig)), dtype=wp.float32),
            wp.zeros_like(d.qfrc_actuator),
            wp.zeros_like(d.sensordata),
            wp.zeros(sim.nworld, dtype=wp.float64),
        )
        clock = wp.zeros(sim.nworld, dtype=wp.float64)
        # io: the contract's bytes each period, float64 (commands up; state, sensordata, time down)
        ncols = len(sim.export_state_interfaces()) + sim.model.nsensordata + 1
        pinned = wp.get_device(sim.device).is_cuda
        up = (wp.zeros(sim.command.shape, dtype=wp.float64, device="cpu", pinned=pinned), wp.zeros(sim.command.shape, dtype=wp.float64))
        down = (wp.zeros((sim.nworld, ncols), dtype=wp.float64), wp.zeros((sim.nworld, ncols), dtype=wp.float64, device="cpu", pinned=pinned))

        def period() -> None:
            if io:
                wp.copy(up[1], up[0])
            if keep_start:  # what batchsim's warp backend copies at the start of each period
                mjw.get_state(mw, d, start[0], sig)
                wp.copy(start[1], d.qfrc_actuator)
                if d.sensordata.size:
                    wp.copy(start[2], d.sensordata)
                wp.copy(start[3], clock)
            for _ in range(NSTEP):
                mjw.step(mw, d)
            if io:
                wp.copy(down[1], down[0])

        period()  # load every kernel before the capture
        with wp.ScopedCapture() as capture:
            period()
        graph = capture.graph

        def body() -> None:
            wp.capture_launch(graph)
            wp.synchronize_device(sim.device)

    body.keep = (mw, d, start, clock, up, down)  # type: ignore[attr-defined]
    body()
    return body


RAW = {"cpu": raw_cpu, "mjx": raw_mjx, "warp": raw_warp}


def raw_overflowed(raw: Callable[[], None]) -> int:
    """How many worlds of raw_warp's Data overflowed a buffer so far. MuJoCo Warp then drops
    contact candidates, contacts or constraint rows without a word (raw_warp turns its warning
    off, as batchsim does): cheaper physics, and wrong."""
    from batchsim.backends.warp.buffers import BUFFER_OVERFLOWS

    d = raw.keep[1]  # type: ignore[attr-defined]
    return int(np.count_nonzero(d.overflow.numpy() & BUFFER_OVERFLOWS))


def unequal_buffers(sim: batchsim.BatchedSystem, built: tuple[int, int], raws: list[Callable[[], None]]) -> str | None:
    """Why a warp measurement compared different physics, or None: the contract grew its
    buffers (nconmax, njmax) after the raw loops were built with `built`, or a raw loop
    overflowed its own. Either way the contract stepped bigger buffers, or more contacts,
    than raw did."""
    now = (sim.nconmax, sim.njmax)
    over = max((raw_overflowed(r) for r in raws), default=0)
    if now == built and not over:
        return None
    why = []
    if now != built:
        why.append(f"the contract grew nconmax {built[0]} -> {now[0]}, njmax {built[1]} -> {now[1]} while raw kept {built}")
    if over:
        why.append(f"raw overflowed its buffers in {over} of {sim.nworld} worlds (it drops contacts silently)")
    return "; ".join(why)
