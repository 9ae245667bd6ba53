"""How steady the host itself is: one fixed piece of work, timed again and again.

    python3 benchmarks/jitter.py [--seconds 20] [--worlds 4096]

The piece is a controller-sized NumPy computation (a cubic spline evaluated for `--worlds`
rows of 6 joints, ~0.1-1 ms), the same inputs every time, on one thread. Each repetition is
timed by the wall clock and by the thread's own clock (CLOCK_THREAD_CPUTIME_ID, which on a
VM that accounts steal leaves the hypervisor's time out), with the thread's involuntary
switches and page faults. A repetition far over the median, with the thread's clock just as
far over and no switch or fault, is time the thread did not get from the machine's cores as
usual, not work: the floor under any loop's worst period on that host. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import resource
import time

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--worlds", type=int, default=4096)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    coeff = rng.normal(size=(4, args.worlds, 6))
    t = rng.uniform(0, 0.025, (args.worlds, 1))

    def work() -> float:
        x = ((coeff[3] * t + coeff[2]) * t + coeff[1]) * t + coeff[0]
        v = (3 * coeff[3] * t + 2 * coeff[2]) * t + coeff[1]
        return float(np.abs(x).max() + np.abs(v).max())

    for _ in range(100):
        work()
    gc.collect()
    gc.freeze()
    wall, cpu, extra = [], [], []
    end = time.perf_counter() + args.seconds
    while time.perf_counter() < end:
        r0 = resource.getrusage(resource.RUSAGE_THREAD)
        c0, w0 = time.thread_time(), time.perf_counter()
        work()
        w1, c1 = time.perf_counter(), time.thread_time()
        r1 = resource.getrusage(resource.RUSAGE_THREAD)
        wall.append(w1 - w0)
        cpu.append(c1 - c0)
        extra.append((r1.ru_nivcsw - r0.ru_nivcsw, r1.ru_minflt - r0.ru_minflt))
    w, c = np.array(wall) * 1e3, np.array(cpu) * 1e3
    med = np.median(w)
    i = int(np.argmax(w))
    far = w > 5 * med
    clean = far & np.array([s == 0 and f == 0 for s, f in extra])
    print(
        f"# {platform.node()} | {os.cpu_count()} cores | python {platform.python_version()} | numpy {np.__version__} | "
        f"{time.strftime('%Y-%m-%d %H:%M')} | load {os.getloadavg()[0]:.1f}"
    )
    print(
        f"{len(w)} repetitions of {args.worlds} x 6 spline rows: wall ms median {med:.3f}, p99 {np.percentile(w, 99):.3f}, "
        f"p99.9 {np.percentile(w, 99.9):.3f}, worst {w[i]:.3f} (the thread's clock in it {c[i]:.3f}, "
        f"{extra[i][0]} involuntary switches, {extra[i][1]} minor faults); over 5x the median: {int(far.sum())}, "
        f"of them {int(clean.sum())} with no switch or fault, their thread clock over 5x its median in "
        f"{int((c[clean] > 5 * np.median(c)).sum())}"
    )


if __name__ == "__main__":
    main()
