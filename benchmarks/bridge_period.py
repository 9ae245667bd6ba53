"""The loop process's per-period work for the bridge (issue 27): `BridgeHost.update`, and the
snapshot into shared memory (tf's body poses of every world among it): in `after_write` when tf
is due, else in `while_stepping`, beside the physics step (on a GPU, the device's), timed alone
per fleet size, with every world's joint_states and tf wanted (as subscribers on every world make
the workers ask; `--no-tf`: joint_states only). No ROS and no workers: the host is driven as
SimLoop.run_period drives it (read, update, write, after_write, one physics step with
while_stepping beside it), unpaced; the figures are the host's own and the contract's read and
write beside them (work may move between them).

    python benchmarks/bridge_period.py --worlds 1024,2048,4096,8192            # cpu backend
    python benchmarks/bridge_period.py --backend warp --devices cpu,cpu        # shard processes
    python benchmarks/bridge_period.py --backend warp --devices 0,1,2,3        # a 4-GPU host

Prints, per fleet size: median and worst per-period after_write, while_stepping, update, read
and write (ms).
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled


def measure(
    model: str, nworld: int, backend: str, devices: list | None, periods: int, tf: bool = True
) -> dict[str, np.ndarray]:
    """Per-period milliseconds of the host's hooks and of read and write, on `nworld` worlds."""
    import batchsim
    from batchsim.controllers import default_controllers, load_controllers
    from batchsim.loop import SimLoop
    from ros_bridge.host import BridgeHost
    from ros_bridge.options import BridgeOptions
    from ros_bridge.plan import build_plan

    options = {"devices": devices, "processes": True} if devices else {}
    sim = batchsim.make(model, nworld, backend, **options)
    sim.configure()
    sim.activate()
    manager = load_controllers(default_controllers(model), sim.spec, nworld)
    loop = SimLoop(sim, control_rate=100.0, rtf=0.0, participants=[manager])
    plan, fills, inputs = build_plan(sim, loop.control_rate, BridgeOptions(), manager, 1)
    host = BridgeHost(sim, loop, plan, fills, inputs, processes=False, manager=manager)  # no workers started
    try:
        wanted = [c for o in plan.outputs if o.topic == "joint_states" for c in o.channels]
        if tf and plan.tf is not None:
            wanted.append(plan.tf.channel)
        host.memory["demand"][:, wanted] = 1  # subscribers on every world's joint_states and tf
        names = ("read", "update", "write", "after_write")
        times: dict[str, list[float]] = {name: [] for name in (*names, "while_stepping")}
        period = 1.0 / loop.control_rate
        for k in range(periods + 5):
            t = k * period
            marks = [time.perf_counter()]
            sim.read(t, period)
            marks.append(time.perf_counter())
            host.update(sim, t, period)
            marks.append(time.perf_counter())
            sim.write(t, period)
            marks.append(time.perf_counter())
            host.after_write(sim, t, period)
            marks.append(time.perf_counter())
            beside = []

            def snapshot(t=t, beside=beside) -> None:  # as SimLoop passes the hook: beside a device's steps
                s = time.perf_counter()
                host.while_stepping(sim, t, period)
                beside.append(time.perf_counter() - s)

            sim.step(1, meanwhile=snapshot)  # one physics step: the engine's poses move on, as in a running loop
            if k >= 5:  # the first periods bind, compile and page in
                for name, a, b in zip(names, marks, marks[1:], strict=False):
                    times[name].append(b - a)
                times["while_stepping"].append(beside[0])
    finally:
        host.close()
        sim.shutdown()
    return {k: np.array(v) * 1e3 for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="arm")
    p.add_argument("--worlds", default="1024,2048,4096,8192", help="fleet sizes, comma-separated")
    p.add_argument("--backend", default="cpu")
    p.add_argument("--devices", default="", help="one shard process per device: cpu,cpu (Warp's CPU device) or 0,1,2,3")
    p.add_argument("--periods", type=int, default=200)
    p.add_argument("--no-tf", action="store_true", help="joint_states wanted only (as benchmarks/fleet.py's subscribers)")
    args = p.parse_args(argv)
    devices = [d if d == "cpu" or ":" in d else int(d) for d in args.devices.split(",")] if args.devices else None
    where = f"{args.backend}" + (f", devices {args.devices} (one shard process each)" if devices else "")
    print(f"# {args.model} on {where}, {args.periods} periods each; ms per period")
    names = ("after_write", "while_stepping", "update", "read", "write")
    print(f"{'worlds':>7} " + " ".join(f"{name + ' median':>18} {'worst':>7}" for name in names))
    for nworld in (int(n) for n in args.worlds.split(",")):
        gc.collect()
        t = measure(args.model, nworld, args.backend, devices, args.periods, tf=not args.no_tf)
        cells = " ".join(f"{np.median(t[name]):>18.3f} {t[name].max():>7.3f}" for name in names)
        print(f"{nworld:>7} {cells}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
