"""Warp's buffers under a long run: 8192 humanoids, 12,000 steps, zero commands.

The incident this answers: with the default sizing (nconmax 24, njmax 117 from the CPU
rollout), 8192 humanoids lying on the floor overflowed the shared contact pool between
steps 1500 and 2000, and every world froze with OVERFLOW. Now the buffers grow and the
period is repeated. This script runs the fleet through the contract (`write(); step(10);
read()` per period) and reports every growth (the backend's log line, the period, and how
long that period took), the frozen worlds at the end, physics steps/s over the run, and the
median and worst wall time of a period.

    python benchmarks/overflow.py                                  # 8192 humanoids, 12,000 steps, on the GPU
    python benchmarks/overflow.py --worlds 4 --steps 400 --device cpu --nconmax 1   # a smoke run anywhere
"""

from __future__ import annotations

import argparse
import datetime
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled

from throughput import device_name, versions  # noqa: E402

import batchsim  # noqa: E402

NSTEP = 10


class _Growths(logging.Handler):
    """Collects the warp backend's log lines, with the period they came in."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.period = 0
        self.lines: list[tuple[int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((self.period, record.getMessage()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="humanoid")
    p.add_argument("--worlds", type=int, default=8192)
    p.add_argument("--steps", type=int, default=12_000, help="physics steps per world (default 12,000)")
    p.add_argument("--device", default=None, help="Warp device (default: Warp's, the GPU if there is one)")
    p.add_argument("--nconmax", type=int, default=None, help="contacts per world to start with (default: sized)")
    p.add_argument("--njmax", type=int, default=None, help="constraint rows per world to start with (default: sized)")
    p.add_argument(
        "--budget", type=float, default=180.0, help="wall seconds for the timed run; it stops early past them (default 180)"
    )
    args = p.parse_args(argv)

    growths = _Growths()
    logger = logging.getLogger("batchsim.warp")
    logger.addHandler(growths)
    logger.propagate = False  # said once, below, not also by the last-resort handler

    print(f"warp buffers over a long run: {args.model}, {args.worlds} worlds, {args.steps} steps, {datetime.date.today()}")
    print(f"{device_name(['warp'])}\n{versions()}", flush=True)
    t0 = time.perf_counter()
    options = {k: v for k, v in (("device", args.device), ("nconmax", args.nconmax), ("njmax", args.njmax)) if v is not None}
    sim = batchsim.make(args.model, args.worlds, "warp", **options)
    sim.configure()
    sim.activate()
    start = (sim.nconmax, sim.njmax)
    sim.command[:] = 0.0
    sim.write()
    sim.step(NSTEP)  # capture the period's graph: not part of the timed run
    sim.read()
    setup = time.perf_counter() - t0
    print(f"setup {setup:.1f} s; buffers nconmax {start[0]}, njmax {start[1]} per world", flush=True)

    nperiod = max(1, args.steps // NSTEP - 1)
    periods = np.empty(nperiod)
    t_run = time.perf_counter()
    for i in range(nperiod):
        if time.perf_counter() - t_run > args.budget:  # the lease is short: report what ran
            print(f"  stopped after {i} periods: over the budget of {args.budget:g} s", flush=True)
            nperiod, periods = i, periods[:i]
            break
        growths.period = i + 1
        t = time.perf_counter()
        sim.write()
        sim.step(NSTEP)
        sim.read()
        periods[i] = time.perf_counter() - t
        if (i + 1) % 200 == 0:
            frozen = int(np.count_nonzero(sim.status))
            print(f"  step {(i + 2) * NSTEP:6d}: sim {sim.time.max():7.2f} s, frozen {frozen}, nconmax {sim.nconmax}, njmax {sim.njmax}", flush=True)
    run = time.perf_counter() - t_run

    steps = nperiod * NSTEP * args.worlds
    frozen = sim.status != 0
    grown = [i for i, _ in growths.lines]
    normal = np.delete(periods, [i - 1 for i in grown if 0 < i <= nperiod])
    print("\ngrowths and other warp lines (period: line, that period's wall time):")
    for i, line in growths.lines:
        print(f"  {i:5d}: {line} ({periods[i - 1] * 1e3:.0f} ms)" if 0 < i <= nperiod else f"  {i:5d}: {line}")
    if not growths.lines:
        print("  none")
    print(
        f"\nsim time {sim.time.max():.2f} s; frozen worlds {int(frozen.sum())} of {args.worlds} "
        f"(OVERFLOW {int((sim.status & batchsim.Status.OVERFLOW != 0).sum())}, "
        f"DIVERGED {int((sim.status & batchsim.Status.DIVERGED != 0).sum())})"
    )
    print(f"buffers: nconmax {start[0]} -> {sim.nconmax}, njmax {start[1]} -> {sim.njmax} per world")
    calm = steps * normal.size / nperiod / normal.sum() if normal.size else float("nan")
    print(f"physics {steps / run:,.0f} steps/s over the run ({run:.1f} s), {calm:,.0f} without the growing periods")
    print(
        f"period of {NSTEP} steps: median {np.median(periods) * 1e3:.2f} ms, worst {periods.max() * 1e3:.1f} ms "
        f"(period {int(periods.argmax()) + 1}); worst without growth {normal.max() * 1e3 if normal.size else 0:.2f} ms"
    )
    print(f"wall time {time.perf_counter() - t0:.1f} s, setup included")
    sim.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
