"""Where one mjx control period's time goes, against the raw jitted MJX loop, at one world count.

throughput.py gives one contract/raw ratio per size. At small sizes on a GPU an MJX period
is a long train of tiny kernels and the ratio moves from run to run, so this script times
the pieces of a period side by side, in many short interleaved rounds whose order rotates,
and reports the median and spread of each:

  raw             the raw loop of throughput.py: jit(lax.scan over NSTEP of vmap(mjx.step)),
                  Data donated, float32 matrix products, block_until_ready
  raw (TF32)      the same at JAX's default matmul precision (TF32 on recent NVIDIA GPUs)
  raw+ctrl        raw taking ctrl as an argument (device_put first), as the contract's program does
  raw+ctrl (NumPy)  the same with ctrl passed as a NumPy array, which JAX uploads itself
  raw+ctrl+readings  and also returning the packed readings (gathered here as the contract
                  gathers them: the program less its check)
  step            sim.step(NSTEP) alone: the contract's upload, period program and download
  contract        sim.command[:] = u; sim.write(); sim.step(NSTEP); sim.read()
  contract(timed) the same, with write, step and read timed apart
  raw (own Data)  raw, stepping a Data of its own rather than the contract's

All but the last step the contract's own Data (`sim.data`, read and assigned), so they
simulate one physical trajectory: an MJX step's cost depends on the contact state, and two
fleets at different moments of their fall differ by more than the contract's overhead.

    python benchmarks/mjx_period.py --worlds 16 --rounds 15
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled

from raw_loops import NSTEP, mjx_rollout  # noqa: E402
from throughput import device_name, versions  # noqa: E402

import batchsim  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="humanoid")
    p.add_argument("--worlds", default="16", help="comma-separated world counts")
    p.add_argument("--rounds", type=int, default=15)
    p.add_argument("--periods", type=int, default=10, help="periods per variant per round")
    args = p.parse_args(argv)
    for nworld in (int(n) for n in args.worlds.split(",")):
        breakdown(args.model, nworld, args.rounds, args.periods)
    return 0


def breakdown(model: str, nworld: int, rounds: int, periods: int) -> None:

    import jax
    import jax.numpy as jnp

    print(f"mjx period breakdown: {model}, {nworld} worlds, {NSTEP} steps per period")
    print(f"{device_name(['mjx'])}\n{versions()}", flush=True)
    sim = batchsim.make(model, nworld, "mjx")
    sim.configure()
    sim.activate()
    m = sim.model
    u = np.random.default_rng(0).uniform(-0.3, 0.3, sim.command.shape)
    ctrl = np.zeros((nworld, m.nu), np.float32)
    ctrl[:, [c.actuator_id for c in sim.spec.commands]] = u
    columns = _read_columns(sim)

    # the raw loop of throughput.py
    rollout, d = mjx_rollout(sim, ctrl)
    own = {"d": d}

    def raw(precision: str | None, on_own_data: bool = False) -> Callable[[], None]:
        def body() -> None:
            with jax.default_matmul_precision(precision):
                if on_own_data:
                    own["d"] = rollout(own["d"])
                else:
                    sim.data = rollout(sim.data)
            jax.block_until_ready((own["d"] if on_own_data else sim.data).qpos)

        return body

    # the raw program, growing step by step into the contract's period program
    def with_ctrl(d, c):
        return rollout(d.replace(ctrl=c))  # inlined into the jit that calls it

    def readings(d):  # the state columns and sensordata, packed as the contract's program packs them
        fields = jnp.concatenate([d.qpos, d.qvel, d.qfrc_actuator, d.sensordata], axis=1)
        return jnp.concatenate([fields[:, columns], d.sensordata], axis=1)

    grown = {
        "raw+ctrl": jax.jit(lambda d, c: (with_ctrl(d, c), jnp.zeros(())), donate_argnums=0),
        "raw+ctrl+readings": jax.jit(
            lambda d, c: (lambda d: (d, readings(d)))(with_ctrl(d, c)), donate_argnums=0
        ),
    }

    def grow(name: str, numpy_ctrl: bool = False) -> Callable[[], None]:
        def body() -> None:
            c = ctrl if numpy_ctrl else jax.device_put(ctrl, sim.device)
            with jax.default_matmul_precision("highest"):
                sim.data, out = grown[name](sim.data, c)
            np.asarray(out)

        return body

    def program() -> None:
        sim.step(NSTEP)

    def contract() -> None:
        sim.command[:] = u
        sim.write()
        sim.step(NSTEP)
        sim.read()

    phases: dict[str, list[float]] = {"write": [], "step": [], "read": []}

    def contract_phases() -> None:
        t0 = time.perf_counter()
        sim.command[:] = u
        sim.write()
        t1 = time.perf_counter()
        sim.step(NSTEP)
        t2 = time.perf_counter()
        sim.read()
        t3 = time.perf_counter()
        for k, dt in zip(phases, (t1 - t0, t2 - t1, t3 - t2), strict=True):
            phases[k].append(dt)

    # every variant but the last steps the contract's own Data: one physical trajectory
    variants: dict[str, Callable[[], None]] = {
        "raw": raw("highest"),
        "raw (TF32)": raw(None),
        "raw+ctrl": grow("raw+ctrl"),
        "raw+ctrl (NumPy)": grow("raw+ctrl", numpy_ctrl=True),
        "raw+ctrl+readings": grow("raw+ctrl+readings"),
        "step": program,
        "contract": contract,
        "contract(timed)": contract_phases,
        "raw (own Data)": raw("highest", on_own_data=True),
    }
    t0 = time.perf_counter()
    for body in variants.values():  # compile and warm
        for _ in range(3):
            body()
    print(f"compiled and warmed in {time.perf_counter() - t0:.1f} s", flush=True)

    names = list(variants)
    per: dict[str, list[float]] = {n: [] for n in names}  # seconds per period, one entry per round
    ratios = []
    for r in range(rounds):
        order = names[r % len(names) :] + names[: r % len(names)]  # rotate who goes first
        for n in order:
            body = variants[n]
            t = time.perf_counter()
            for _ in range(periods):
                body()
            per[n].append((time.perf_counter() - t) / periods)
        ratios.append(per["raw"][-1] / per["contract"][-1])

    print(
        f"\n{'variant':18s} {'median ms':>10s} {'p10':>8s} {'p90':>8s} {'steps/s':>10s}  (per period, {rounds} rounds)"
    )
    for n in names:
        x = np.array(per[n]) * 1e3
        print(
            f"{n:18s} {np.median(x):10.3f} {np.percentile(x, 10):8.3f} {np.percentile(x, 90):8.3f} "
            f"{nworld * NSTEP / np.median(x) * 1e3:10,.0f}"
        )
    print(
        "\ninside contract(timed), median ms: "
        + ", ".join(
            f"{k} {np.median(v) * 1e3:.3f} (p90 {np.percentile(v, 90) * 1e3:.3f})" for k, v in phases.items()
        )
    )
    ratios = np.array(ratios)
    print(
        f"\ncontract/raw per round: median {np.median(ratios):.3f}, min {ratios.min():.3f}, "
        f"max {ratios.max():.3f}; ratio of medians {np.median(per['raw']) / np.median(per['contract']):.3f}"
    )
    sim.shutdown()


def _read_columns(sim: batchsim.BatchedSystem) -> np.ndarray:
    """Where each read() column (state interfaces, then the floating base) sits in the
    concatenation qpos | qvel | qfrc_actuator | sensordata, from the public spec."""
    m = sim.model
    offset = {"qpos": 0, "qvel": m.nq, "qfrc_actuator": m.nq + m.nv, "sensordata": m.nq + 2 * m.nv}
    columns = [offset[c.source.value] + c.index for c in sim.spec.state]
    base = sim.spec.floating_base
    if base is not None:
        columns += [base.qposadr + k for k in range(7)] + [m.nq + base.dofadr + k for k in range(6)]
    return np.array(columns, dtype=np.int32)


if __name__ == "__main__":
    sys.exit(main())
