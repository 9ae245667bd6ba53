"""What a fleet's shard processes cost per control period, on CPU devices: the fleet's wait
for each part of a period (the commands put in, `write()`, `step(n)`, `read()`) against the
slowest shard process's own time for it (ProcessShard.busy); the difference is the messages
to and from the shard processes and the wait for the slowest. No GPU needed: Warp's CPU
device stands in for each GPU. Few worlds of a small model show the fixed costs; many show
what grows with the fleet (the commands' copy in the fleet's process).

    python benchmarks/shard_round_trip.py --shards 2 --worlds 1 --model arm         # the messages
    python benchmarks/shard_round_trip.py --shards 1 --worlds 8192 --model humanoid # the copies
    python benchmarks/shard_round_trip.py --counts 0,1,2,4 --worlds 1               # by shard count
    python benchmarks/shard_round_trip.py --counts 2,4 --worlds 2048 --model humanoid --commands assign,set
    python benchmarks/shard_round_trip.py --spin on    # poll for messages even on few cores

`--counts`: shard processes per fleet, one fleet each (0: one system in this process, no
shards: the baseline). `--commands`: how each period's commands go in, `set` (`sim.command =
...`: ShardedSystem.set_command) or `assign` (`sim.command[:] = ...`), each one copy in this
process. Prints, per fleet and call, the medians over `--calls` periods: the fleet's wait,
the slowest shard's own time, their difference, and when the request had reached the last
shard and the last shard was done (us from the call's start; perf_counter is one clock for
every process on Linux).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled

import batchsim  # noqa: E402
from batchsim.backends import backend_class, sharded  # noqa: E402
from batchsim.backends.sharded import ShardedSystem  # noqa: E402

OPS = ("write", "step", "read")


def fleet(model: str, worlds: int, nshard: int) -> batchsim.BatchedSystem:
    """`nshard` shard processes of `worlds` worlds each on Warp's CPU device, active (0: one
    system of `worlds` in this process)."""
    if nshard == 0:
        sim = batchsim.make(model, worlds, "warp", device="cpu")
    else:
        cls = backend_class(batchsim.Backend.parse("warp"))
        sim = ShardedSystem(cls, batchsim.load(model), worlds * nshard, ["cpu"] * nshard, processes=True)
        sim.initialize()
    sim.configure()
    sim.activate()
    return sim


def periods(sim: batchsim.BatchedSystem, commands: str, nstep: int, calls: int) -> dict[str, np.ndarray]:
    """Median us of each part of `calls` periods: the fleet's wait (set, write, step, read) and,
    with shard processes, per call the slowest shard's own time, when the request had reached
    the last shard and when the last shard was done (from the call's start)."""
    shards = getattr(sim, "shards", [])
    command = np.random.default_rng(0).uniform(-0.3, 0.3, sim.command.shape)

    def put() -> None:
        if commands == "set":
            sim.command = command
        else:
            sim.command[:] = command

    def shard_times(start: float) -> tuple[float, float, float]:
        if not shards:
            return 0.0, 0.0, 0.0
        return (
            max(s.busy for s in shards),
            max(s.began for s in shards) - start,
            max(s.began + s.busy for s in shards) - start,
        )

    calls_ = (sim.write, lambda: sim.step(nstep), sim.read)
    waits, own = [], []
    for i in range(calls + 3):  # the first period of a length compiles
        t0 = time.perf_counter()
        put()
        wait, mine = [time.perf_counter() - t0], []
        for call in calls_:
            start = time.perf_counter()
            call()
            wait.append(time.perf_counter() - start)
            mine.append(shard_times(start))
        if i >= 3:
            waits.append(wait)
            own.append(mine)
    return {"wait": np.median(waits, axis=0) * 1e6, "shard": np.median(own, axis=0) * 1e6}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shards", type=int, default=2, help="shard processes, each on Warp's CPU device")
    p.add_argument("--counts", default="", help="shard counts to run, one fleet each (0: no shards); default --shards")
    p.add_argument("--worlds", type=int, default=1, help="worlds per shard")
    p.add_argument("--model", default="arm")
    p.add_argument("--nstep", type=int, default=1, help="physics steps per period")
    p.add_argument("--calls", type=int, default=300, help="timed periods")
    p.add_argument("--commands", default="set", help="set (sim.command = ...), assign ([:] =), or both")
    p.add_argument("--spin", choices=("auto", "on", "off"), default="auto", help="poll for messages (auto: where cores allow)")
    args = p.parse_args(argv)
    if args.spin != "auto":  # the fleet's choice of polling, made for it
        sharded.spin_budget = lambda nshard: 0.05 if args.spin == "on" else 0.0  # type: ignore[assignment]
    counts = [int(k) for k in args.counts.split(",") if k.strip()] or [args.shards]
    puts = [c.strip() for c in args.commands.split(",") if c.strip()]
    print(f"{args.worlds} {args.model} per shard, Warp's CPU device, step({args.nstep}), {args.calls} periods each")
    for nshard in counts:
        for commands in puts:
            sim = fleet(args.model, args.worlds, nshard)
            what = (
                f"{nshard} shard processes, polling {sim.shards[0].spin > 0}"
                if nshard
                else "one system in this process"
            )
            times = periods(sim, commands, args.nstep, args.calls)
            sim.shutdown()
            print(f"{what}, commands {commands}:")
            print(f"  {'commands':8s} fleet {times['wait'][0]:9.1f} us")
            for k, name in enumerate(OPS):
                wait, (own, began, done) = times["wait"][k + 1], times["shard"][k]
                line = f"  {name:8s} fleet {wait:9.1f} us"
                if nshard:
                    line += (
                        f"   slowest shard {own:9.1f} us   messages {wait - own:8.1f} us"
                        f"   (at the last shard +{began:.1f}, last done +{done:.1f})"
                    )
                print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
