"""What per-world randomization and the vector env cost (issue 26), measured side by side in one run.

  randomized   the contract loop (command, write, step, read) on a fleet whose masses,
               frictions and servo gains are drawn per world, against the same fleet
               unrandomized, interleaved in rounds (throughput.py's `interleaved`); and a
               fleet with the same fields batched per world but drawn at their nominal values
               (scale 1), against a plain fleet started with it: the same physics, so its
               ratio is what per-world fields cost the engine, apart from what other masses
               do to a falling humanoid's contacts
  resets       the randomized fleet with 10 % of its worlds reset with fresh draws every
               simulated second (every `control rate` periods; flat out, so far more often
               than every wall-clock second), against the same fleet without resets; and the
               reset call's own time, median and worst
  vector       batchsim.vector's step (host arrays) against the contract loop it runs on, the
               same worlds; with --device also device=True (warp/mjx: no host copy of state
               or actions), against the contract's own device path (write_device, step,
               device_state)

    python benchmarks/variation.py --backend warp --model humanoid --worlds 8192 --device
    python benchmarks/variation.py --backend cpu --model humanoid --worlds 256

Prints a line per measurement and writes JSON to --out (steps/s = worlds * nstep / s).
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled
sys.path.insert(0, str(Path(__file__).resolve().parent))

from raw_loops import NSTEP  # noqa: E402
from throughput import device_name, interleaved, rate, versions  # noqa: E402

import batchsim  # noqa: E402
from batchsim import vector  # noqa: E402

VARIATION = {
    "seed": 1,
    "redraw_on_reset": True,
    "fields": [
        {"field": "body_mass", "also": ["body_inertia"], "scale": {"uniform": [0.8, 1.2]}},
        {"field": "geom_friction", "columns": [0], "scale": {"uniform": [0.5, 1.5]}},
        {"field": "actuator_gainprm", "columns": [0], "scale": {"uniform": [0.8, 1.2]}},
    ],
}


IDENTITY = {  # the same fields batched per world, each drawn at its nominal value
    "seed": 1,
    "redraw_on_reset": True,
    "fields": [{**f, "scale": {"uniform": [1.0, 1.0]}} for f in VARIATION["fields"]],
}
WARMUP = 20  # periods each fleet runs before timing: warp's buffers grow in the first ones


def made(args: argparse.Namespace, randomize: dict | None) -> batchsim.BatchedSystem:
    options = {"nconmax": args.nconmax} if args.nconmax is not None else {}
    sim = batchsim.make(args.model, args.worlds, args.backend, randomize=randomize, **options)
    sim.configure()
    sim.activate()
    return sim


def loop(sim: batchsim.BatchedSystem, u: np.ndarray):
    def body() -> None:
        sim.command[:] = u
        sim.write()
        sim.step(NSTEP)
        sim.read()

    return body


def zeros_on_device(sim: batchsim.BatchedSystem, shape: tuple[int, ...]):
    """A zero float32 action array on the engine's device, of the backend's own kind."""
    if sim.name == "warp":
        import warp as wp

        return wp.zeros(shape, dtype=wp.float32, device=sim.device)
    if sim.name == "mjx":
        import jax
        import jax.numpy as jnp

        return jax.device_put(jnp.zeros(shape, jnp.float32), sim.device)
    return np.zeros(shape)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backend", default="cpu")
    p.add_argument("--model", default="humanoid")
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--seconds", type=float, default=3.0, help="timed seconds per side")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--warmup", type=int, default=WARMUP, help="periods each fleet runs before timing")
    p.add_argument(
        "--nconmax", type=int, default=None,
        help="warp: contacts per world to start with (large enough, no fleet grows its buffers while timed)",
    )
    p.add_argument(
        "--reset-every", type=float, default=None, metavar="SECONDS",
        help="reset 10%% of the worlds every SECONDS of wall-clock time instead of every simulated second",
    )
    p.add_argument("--device", action="store_true", help="also the vector env's device=True (warp, mjx)")
    p.add_argument("--out", default="benchmarks/out/variation.json")
    args = p.parse_args(argv)
    rows: dict = {
        "date": datetime.date.today().isoformat(),
        "machine": device_name([args.backend]),
        "versions": versions(),
        "backend": args.backend,
        "model": args.model,
        "nworld": args.worlds,
        "nstep": NSTEP,
    }
    work = args.worlds * NSTEP

    # --- randomized against plain, interleaved ---
    plain, varied, same = made(args, None), made(args, VARIATION), made(args, IDENTITY)
    u = np.zeros((args.worlds, len(plain.spec.commands)))
    t0 = time.perf_counter()
    for sim in (varied, plain, same):  # the first period compiles (mjx) or captures (warp): not timed
        for _ in range(args.warmup):
            loop(sim, u)()
    print(f"first periods (compile/capture, {args.warmup} each): {time.perf_counter() - t0:.1f} s", flush=True)
    vs, ps, ratios, _ = interleaved(loop(varied, u), loop(plain, u), work, args.seconds, args.rounds)
    rows["randomized"] = {"varied_sps": vs, "plain_sps": ps, "ratio": vs / ps, "round_ratios": ratios}
    spread = ", ".join(f"{r:.3f}" for r in ratios)
    print(f"randomized/plain: {vs / ps:.3f} ({vs:,.0f} vs {ps:,.0f} steps/s; rounds {spread})")
    fresh = made(args, None)  # a plain fleet at the identity fleet's moment of the fall
    for _ in range(args.warmup):
        loop(fresh, u)()
    ss, fs, ratios, _ = interleaved(loop(same, u), loop(fresh, u), work, args.seconds, args.rounds)
    rows["batched_nominal"] = {"batched_sps": ss, "plain_sps": fs, "ratio": ss / fs, "round_ratios": ratios}
    spread = ", ".join(f"{r:.3f}" for r in ratios)
    print(f"fields batched at nominal values/plain: {ss / fs:.3f} ({ss:,.0f} vs {fs:,.0f} steps/s; rounds {spread})")
    del same, fresh

    # --- 10 % of the worlds reset with fresh draws every simulated second ---
    rng = np.random.default_rng(0)
    every = max(1, round(1.0 / (NSTEP * varied.dt)))  # control periods per simulated second
    count = [0]
    reset_times: list[float] = []

    last = [time.perf_counter()]

    def due() -> bool:
        if args.reset_every is None:
            return count[0] % every == 0
        if time.perf_counter() - last[0] < args.reset_every:
            return False
        last[0] = time.perf_counter()
        return True

    def with_resets() -> None:
        loop(varied, u)()
        count[0] += 1
        if due():
            worlds = rng.choice(args.worlds, max(1, args.worlds // 10), replace=False)
            t = time.perf_counter()
            varied.reset(np.sort(worlds))
            reset_times.append(time.perf_counter() - t)

    rs, ns, ratios, _ = interleaved(with_resets, loop(varied, u), work, args.seconds, args.rounds)
    med, worst = (float(np.median(reset_times)), float(np.max(reset_times))) if reset_times else (0.0, 0.0)
    rows["resets"] = {
        "with_sps": rs,
        "without_sps": ns,
        "ratio": rs / ns,
        "periods_between": every,
        "resets": len(reset_times),
        "reset_median_s": med,
        "reset_worst_s": worst,
    }
    when = f"{args.reset_every:g} s of wall time" if args.reset_every is not None else f"{every} periods"
    rows["resets"]["every"] = when
    print(
        f"10% reset every {when} / none: {rs / ns:.3f} ({rs:,.0f} vs {ns:,.0f} steps/s); "
        f"reset() of {max(1, args.worlds // 10)} worlds: median {med * 1e3:.2f} ms, worst {worst * 1e3:.2f} ms ({len(reset_times)} resets)"
    )
    del plain

    # --- the vector env against the contract loop it runs on ---
    env = vector.BatchsimVectorEnv(varied, nstep=NSTEP, autoreset_mode="Disabled")
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape)
    es, cs, ratios, _ = interleaved(
        lambda: env.step(action), loop(varied, u), work, args.seconds, args.rounds
    )
    rows["vector"] = {"env_sps": es, "contract_sps": cs, "ratio": es / cs}
    print(f"vector env (host arrays)/contract: {es / cs:.3f} ({es:,.0f} vs {cs:,.0f} steps/s)")
    if args.device:
        denv = vector.BatchsimVectorEnv(varied, nstep=NSTEP, autoreset_mode="Disabled", device=True)
        denv.reset(seed=0)
        dev_action = zeros_on_device(varied, action.shape)

        def contract_device() -> None:
            varied.write_device(dev_action)
            varied.step(NSTEP)
            varied.device_state()

        denv.step(dev_action)
        contract_device()
        ds, dcs, ratios, _ = interleaved(
            lambda: denv.step(dev_action), contract_device, work, args.seconds, args.rounds
        )
        host_again = rate(lambda: env.step(action), max(3, int(args.seconds * es / work / args.rounds)), work)
        rows["vector_device"] = {
            "env_sps": ds,
            "contract_device_sps": dcs,
            "ratio": ds / dcs,
            "host_env_sps": host_again,
        }
        print(
            f"vector env (device arrays)/contract device path: {ds / dcs:.3f} ({ds:,.0f} vs {dcs:,.0f} steps/s); "
            f"host-array env just after: {host_again:,.0f} steps/s"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    print(f"machine: {rows['machine']}; {rows['versions']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
