"""What the contract costs on the cpu backend: raw mujoco.batch.Batch against the contract loop.

Both sides do the same physics in the same process, interleaved, on the same thread count:

  raw:      ctrl[:] = u; batch.step(nstep=10); qpos.copy(), qvel.copy(), sensordata.copy()
  contract: sim.command[:] = u; sim.write(); sim.step(10); sim.read()

Prints a table of physics steps/s (nworld * nstep / seconds) and, as its last line,
`ratio <lowest contract/raw>`.

    python benchmarks/overhead.py [--models arm,quadruped] [--worlds 1,16,256] [--seconds 2]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import mujoco
import numpy as np
from mujoco import batch as mjbatch

import batchsim

NSTEP = 10


def time_loop(body, seconds: float) -> float:
    """Median seconds per call of body over `seconds`, after a warm-up."""
    for _ in range(3):
        body()
    samples = []
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline or len(samples) < 5:
        t0 = time.perf_counter()
        for _ in range(5):
            body()
        samples.append((time.perf_counter() - t0) / 5)
    return float(np.median(samples))


def measure(model: str, nworld: int, seconds: float, nthread: int) -> tuple[float, float]:
    sim = batchsim.make(model, nworld, "cpu", nthread=nthread)
    sim.configure()
    sim.activate()
    rng = np.random.default_rng(0)
    u = rng.uniform(-0.1, 0.1, sim.command.shape)

    raw = mjbatch.Batch(sim.model, nworld, nthread=sim.nthread)
    ctrl, qpos, qvel, sensordata = (raw.bind(f) for f in ("ctrl", "qpos", "qvel", "sensordata"))
    act = [c.actuator_id for c in sim.spec.commands]

    def raw_period():
        ctrl[:, act] = u
        raw.step(nstep=NSTEP)
        qpos.copy(), qvel.copy(), sensordata.copy()

    def contract_period():
        sim.command[:] = u
        sim.write()
        sim.step(NSTEP)
        sim.read()

    # interleave so that both see the same machine state; best of three rounds each
    raw_t, con_t = [], []
    for _ in range(3):
        raw_t.append(time_loop(raw_period, seconds / 6))
        con_t.append(time_loop(contract_period, seconds / 6))
        raw.reset()
        sim.reset()
    sim.shutdown()
    steps = nworld * NSTEP
    return steps / min(raw_t), steps / min(con_t)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", default="arm,quadruped")
    p.add_argument("--worlds", default="1,16,256")
    p.add_argument("--seconds", type=float, default=3.0, help="per (model, worlds) pair")
    p.add_argument("--threads", type=int, default=0, help="0: one per core, capped at the world count")
    args = p.parse_args()

    print(
        f"# {platform.node()} | {os.cpu_count()} cores | {platform.processor() or platform.machine()} | "
        f"python {platform.python_version()} | mujoco {mujoco.__version__} | numpy {np.__version__} | "
        f"{time.strftime('%Y-%m-%d')}"
    )
    print(f"{'model':10s} {'worlds':>6s} {'raw steps/s':>14s} {'contract steps/s':>17s} {'ratio':>6s}")
    ratios = []
    for model in args.models.split(","):
        for nworld in (int(n) for n in args.worlds.split(",")):
            nthread = args.threads or min(nworld, os.cpu_count() or 1)
            raw, contract = measure(model, nworld, args.seconds, nthread)
            ratio = contract / raw
            ratios.append(ratio)
            print(f"{model:10s} {nworld:6d} {raw:14,.0f} {contract:17,.0f} {ratio:6.3f}", flush=True)
    print(f"ratio {min(ratios):.3f}")


if __name__ == "__main__":
    main()
