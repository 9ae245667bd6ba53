"""What a fleet's shard processes cost per contract call, on CPU devices: the fleet's wait
for `write()`, `step(1)` and `read()` against the slowest shard process's own time for it
(ProcessShard.busy); the difference is the messages to and from the shard processes and
the wait for the slowest. No GPU needed: Warp's CPU device stands in for each GPU.

    python benchmarks/shard_round_trip.py --shards 2 --worlds 1 --model arm         # the messages
    python benchmarks/shard_round_trip.py --shards 1 --worlds 8192 --model humanoid # the copies
    python benchmarks/shard_round_trip.py --spin on    # poll for messages even on few cores

Prints one line per call: median fleet wait, median slowest shard, their difference (us).
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shards", type=int, default=2, help="shard processes, each on Warp's CPU device")
    p.add_argument("--worlds", type=int, default=1, help="worlds per shard")
    p.add_argument("--model", default="arm")
    p.add_argument("--calls", type=int, default=300, help="timed calls of each kind")
    p.add_argument("--spin", choices=("auto", "on", "off"), default="auto", help="poll for messages (auto: where cores allow)")
    args = p.parse_args(argv)
    if args.spin != "auto":  # the fleet's choice of polling, made for it
        sharded.spin_budget = lambda nshard: 0.05 if args.spin == "on" else 0.0  # type: ignore[assignment]
    cls = backend_class(batchsim.Backend.parse("warp"))
    sim = ShardedSystem(cls, batchsim.load(args.model), args.worlds * args.shards, ["cpu"] * args.shards, processes=True)
    sim.initialize()
    sim.configure()
    sim.activate()
    sim.command[:] = np.random.default_rng(0).uniform(-0.3, 0.3, sim.command.shape)
    for _ in range(3):  # the first period of a length compiles
        sim.write()
        sim.step(1)
        sim.read()
    print(
        f"{args.shards} shard processes x {args.worlds} {args.model}, Warp's CPU device, "
        f"polling {sim.shards[0].spin > 0}, {args.calls} calls each"
    )
    for name, call in (("write", sim.write), ("step(1)", lambda: sim.step(1)), ("read", sim.read)):
        waits, busy = [], []
        for _ in range(args.calls):
            t0 = time.perf_counter()
            call()
            waits.append(time.perf_counter() - t0)
            busy.append(max(s.busy for s in sim.shards))
        wait, own = np.median(waits) * 1e6, np.median(busy) * 1e6
        print(f"{name:8s} fleet waits {wait:9.1f} us   slowest shard {own:9.1f} us   messages {wait - own:8.1f} us")
    sim.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
