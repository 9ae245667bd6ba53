"""Where a world of K robots loses to K worlds of one, in raw MuJoCo Warp (no batchsim in the loop).

`fleet_robots.py physics` measures the ratio through the contract; this script takes the very
models batchsim composes (fleet_robots.fleet_of: K robots on one floor, 3 m apart) and steps
them with MuJoCo Warp alone: put_model, put_data (batchsim's buffer sizes), one captured graph
of `nstep` mjw.step calls, replayed. It prints per layout the robot-steps/s and, with MuJoCo
Warp's own EventTracer, each phase's device time per robot-step, so the phase whose cost grows
with the robots a world holds stands out. `--override` variants (MuJoCo Warp's notation, as
`mjwarp-testspeed -o`: "opt.solver=cg", "opt.jacobian=dense") are measured in the same run,
each against its own one-robot layout.

  python benchmarks/robots_per_world_kernels.py --model rover --robots 4,8 --total 8192 \
      --variant default --variant opt.solver=cg --variant opt.jacobian=dense
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _model(name: str, k: int):
    from fleet_robots import fleet_of

    from batchsim.fleet.compose import compose
    from batchsim.fleet.file import read_fleet

    return compose(read_fleet(fleet_of(name, k))).mjmodel


def _flatten(trace: dict, prefix: str = "") -> dict[str, float]:
    out: dict[str, float] = {}
    for key, (times, sub) in trace.items():
        out[prefix + key] = out.get(prefix + key, 0.0) + float(sum(times))
        for k2, v2 in _flatten(sub, prefix + key + ".").items():
            out[k2] = out.get(k2, 0.0) + v2
    return out


def measure(mjm, nworld: int, nstep: int, seconds: float, overrides: list[str], trace: bool) -> tuple[float, dict]:
    """(world-steps/s, {phase: ms summed over the traced launches}) of `nstep`-step graphs."""
    import mujoco
    import mujoco_warp as mjw
    import warp as wp
    from mujoco_warp._src import warp_util
    from mujoco_warp._src.io import override_model

    from batchsim.backends.warp.buffers import rollout_sizes

    if overrides:
        mjm = copy.copy(mjm)
        override_model(mjm, [o for o in overrides if o.split("=")[0].strip() in ("opt.jacobian",)])
    nconmax, njmax = rollout_sizes(mjm)
    mjd = mujoco.MjData(mjm)
    mujoco.mj_forward(mjm, mjd)
    m = mjw.put_model(mjm)
    rest = [o for o in overrides if o.split("=")[0].strip() not in ("opt.jacobian",)]
    if rest:
        override_model(m, rest)
    m.opt.warn_overflow = 0
    d = mjw.put_data(mjm, mjd, nworld=nworld, nconmax=max(nconmax, mjd.ncon), njmax=max(njmax, mjd.nefc))

    def program() -> None:
        for _ in range(nstep):
            mjw.step(m, d)

    program()  # compile outside the capture
    wp.synchronize()
    cuda = wp.get_device().is_cuda
    if cuda:
        with wp.ScopedCapture() as capture:
            program()
    run = (lambda: wp.capture_launch(capture.graph)) if cuda else program  # Warp's CPU: no graphs
    for _ in range(3):
        run()
    wp.synchronize()
    launches, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        run()
        wp.synchronize()
        launches += 1
    rate = nworld * nstep * launches / (time.perf_counter() - start)
    phases: dict[str, float] = {}
    if trace and cuda:  # a second graph, captured with the tracer's events in it (CUDA events only)
        with warp_util.EventTracer(enabled=True) as tracer:
            with wp.ScopedCapture() as capture:
                program()
            for _ in range(5):
                wp.capture_launch(capture.graph)
                wp.synchronize()
                for key, value in _flatten(tracer.trace()).items():
                    phases[key] = phases.get(key, 0.0) + value
        phases = {k: v / 5 for k, v in phases.items()}  # ms per launch of nstep steps
    return rate, phases


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="rover")
    p.add_argument("--robots", default="4,8", type=lambda s: [int(x) for x in s.split(",")])
    p.add_argument("--total", type=int, default=8192)
    p.add_argument("--nstep", type=int, default=10)
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--variant", action="append", default=None, help="'default' or overrides joined by ';'")
    p.add_argument("--no-trace", action="store_true")
    p.add_argument("--depth", type=int, default=2, help="phase names shown down to this depth")
    opts = p.parse_args()
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    wp.config.quiet = True
    wp.init()
    dev = wp.get_device()
    print(f"# {dev.name if dev.is_cuda else 'cpu'}; mujoco {mujoco.__version__}, mujoco_warp "
          f"{getattr(mjw, '__version__', '?')}, warp {wp.__version__}; model {opts.model}, "
          f"{opts.total} robots, {opts.nstep} steps a graph")
    variants = opts.variant or ["default"]
    for variant in variants:
        overrides = [] if variant == "default" else [o for o in variant.split(";") if o]
        results = {}
        for k in [1, *opts.robots]:
            mjm = _model(opts.model, k)
            nworld = max(1, opts.total // k)
            try:
                rate, phases = measure(mjm, nworld, opts.nstep, opts.seconds, overrides, not opts.no_trace)
            except ValueError as e:  # MuJoCo Warp refuses the variant for this model (dense above nv 60)
                print(f"variant {variant}, {k} robots a world: {e}", flush=True)
                continue
            results[k] = (rate * k, phases, nworld, mjm.nv)
        print(f"\n## variant {variant}")
        if 1 not in results:
            continue
        print(f"{'robots/world':>12s} {'worlds':>6s} {'nv':>4s} {'robot-steps/s':>14s} {'ratio':>6s}")
        for k, (rate, _, nworld, nv) in results.items():
            print(f"{k:12d} {nworld:6d} {nv:4d} {rate:14.0f} {rate / results[1][0]:6.3f}")
        if opts.no_trace or not results[1][1]:
            continue
        keys = [key for key in results[1][1] if key.count(".") < opts.depth]
        print(f"{'phase (ns per robot-step)':40s}" + "".join(f"{'K=' + str(k):>10s}" for k in results))
        for key in keys:
            row = []
            for k, (_, phases, nworld, _) in results.items():
                row.append(1e6 * phases.get(key, 0.0) / (nworld * k * opts.nstep))  # ms -> ns per robot-step
            print(f"{key:40s}" + "".join(f"{v:10.1f}" for v in row))


if __name__ == "__main__":
    main()
