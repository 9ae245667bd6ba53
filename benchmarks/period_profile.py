"""Where a control period's time goes through the contract, against the raw library's period.

    python3 benchmarks/period_profile.py --backend warp --worlds 8192 --model humanoid

Times, in one process and interleaved, the raw loop (benchmarks/throughput.py's: NSTEP steps
captured in one graph, launched and synchronized; for mjx the jitted scan), the contract's
period (`command[:] = u; write(); step(NSTEP); read()`) and its device path
(`write_device(u); step(NSTEP); device_state()`: nothing through the host), then runs the contract's periods
once more under cProfile and prints, per period, each function's own time and its time with
what it calls (the functions that take at least 1 % of a period), so that the gap between
the two periods can be read off as launches, synchronizations (the wait for the device is
inside `synchronize_device` / `block_until_ready`), copies and Python. cProfile's own cost
inflates the profiled period: read the shares, and the unprofiled medians for the totals.
Every side steps a fleet of its own the same number of periods, so that all are at the same
moment of the motion when timed (an 8192-humanoid step costs more or less as they fall).
Nothing is asserted.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from raw_loops import NSTEP, raw_mjx, raw_warp, unequal_buffers  # noqa: E402

import batchsim  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--backend", default="warp", choices=["warp", "mjx"])
    p.add_argument("--worlds", type=int, default=8192)
    p.add_argument("--model", default="humanoid")
    p.add_argument("--periods", type=int, default=200)
    p.add_argument("--rounds", type=int, default=3)
    opts = p.parse_args()
    grown = profile(opts, None)
    if grown is not None:  # the contract's buffers grew, or raw's overflowed: not the same physics
        print(f"# measured again from the start, every side at nconmax {grown[0]}, njmax {grown[1]}")
        profile(opts, grown)


def profile(opts: argparse.Namespace, buffers: tuple[int, int] | None) -> tuple[int, int] | None:
    """Time and profile one fleet; on warp, the (nconmax, njmax) to measure again with when the
    contract grew its buffers after raw was built or raw overflowed its own (None: the same physics)."""
    sizing = {} if buffers is None else {"nconmax": buffers[0], "njmax": buffers[1]}
    sim = batchsim.make(opts.model, opts.worlds, opts.backend, **sizing)
    sim.configure()
    sim.activate()
    # the device path steps a fleet of its own: on the contract's, that fleet ran two periods for
    # every one of raw's, at a later and cheaper moment of the humanoids' fall (0.97 read here
    # where throughput.py, every side at the same moment, read 0.95 on the same H100)
    dsim = batchsim.make(opts.model, opts.worlds, opts.backend, **sizing)
    dsim.configure()
    dsim.activate()
    u = np.random.default_rng(0).uniform(-0.2, 0.2, sim.command.shape)
    ctrl = u[:, : sim.model.nu] if sim.model.nu else u
    built = (sim.nconmax, sim.njmax) if opts.backend == "warp" else (0, 0)
    raw = (raw_warp if opts.backend == "warp" else raw_mjx)(sim, ctrl)
    # warp: the raw loop that also keeps the period's start and moves the contract's bytes
    # (commands up, state down): the floor under any loop that commands from the host
    floor = raw_warp(sim, ctrl, keep_start=True, io=True) if opts.backend == "warp" else None

    def contract() -> None:
        sim.command[:] = u
        sim.write()
        sim.step(NSTEP)
        sim.read()

    device_u = None
    if opts.backend == "warp":  # the contract's device path: commands and state stay on the GPU
        import warp as wp

        device_u = wp.array(u.astype(np.float32), dtype=wp.float32, device=dsim.device)
    else:
        import jax

        device_u = jax.device_put(u.astype(np.float32), dsim.device)

    def device() -> None:
        dsim.write_device(device_u)
        dsim.step(NSTEP)
        dsim.device_state()

    for _ in range(20):  # compile, capture, settle
        contract()
        raw()
        device()
        if floor is not None:
            floor()
    print(f"# {platform.node()} | {sim.device} | {opts.model} x {opts.worlds} on {opts.backend}, {NSTEP} steps a period")
    print(f"# python {platform.python_version()}, {time.strftime('%Y-%m-%d')}")
    sides: dict[str, list[float]] = {"raw": [], "contract": [], "write": [], "step": [], "read": [], "device": [], "floor": []}
    for _ in range(opts.rounds):
        for _ in range(opts.periods if floor is not None else 0):
            t0 = time.perf_counter()
            floor()
            sides["floor"].append(time.perf_counter() - t0)
        for _ in range(opts.periods):
            t0 = time.perf_counter()
            raw()
            sides["raw"].append(time.perf_counter() - t0)
        for _ in range(opts.periods):
            t0 = time.perf_counter()
            device()
            sides["device"].append(time.perf_counter() - t0)
        for _ in range(opts.periods):
            t0 = time.perf_counter()
            sim.command[:] = u
            sim.write()
            t1 = time.perf_counter()
            sim.step(NSTEP)
            t2 = time.perf_counter()
            sim.read()
            t3 = time.perf_counter()
            sides["contract"].append(t3 - t0)
            sides["write"].append(t1 - t0)
            sides["step"].append(t2 - t1)
            sides["read"].append(t3 - t2)
    unequal = unequal_buffers(sim, built, [raw, floor]) if floor is not None else None
    if unequal is not None:
        print(f"NOT THE SAME PHYSICS: {unequal}")
        if buffers is None:
            sim.shutdown()
            dsim.shutdown()
            return (sim.nconmax, sim.njmax) if (sim.nconmax, sim.njmax) != built else (2 * built[0], 2 * built[1])
    med = {k: 1e3 * statistics.median(v) for k, v in sides.items() if v}
    mean = {k: 1e3 * statistics.fmean(v) for k, v in sides.items() if v}
    worst = {k: 1e3 * max(v) for k, v in sides.items() if v}
    print(
        f"period median: raw {med['raw']:.3f} ms, contract {med['contract']:.3f} ms "
        f"(command+write {med['write']:.3f}, step {med['step']:.3f}, read {med['read']:.3f}); "
        f"ratio contract/raw steps/s {med['raw'] / med['contract']:.3f}; gap {med['contract'] - med['raw']:.3f} ms"
    )
    print(
        f"device path (write_device, step, device_state): {med['device']:.3f} ms, "
        f"ratio to raw steps/s {med['raw'] / med['device']:.3f}"
    )
    if "floor" in med:
        print(
            f"raw + keep + io (the start kept, the contract's bytes moved): {med['floor']:.3f} ms, "
            f"ratio to raw {med['raw'] / med['floor']:.3f}; the contract at {med['floor'] / med['contract']:.3f} of it"
        )
    print(
        "mean (worst) ms: " + ", ".join(f"{k} {mean[k]:.3f} ({worst[k]:.2f})" for k in ("raw", "contract", "device", "floor") if k in mean)
        + f"; ratio of means contract/raw {mean['raw'] / mean['contract']:.3f}"
    )
    if opts.backend == "warp":
        probe_host(sim, u, opts.periods)
    profile = cProfile.Profile()
    profile.enable()
    for _ in range(opts.periods):
        contract()
    profile.disable()
    stats = pstats.Stats(profile)
    total = sum(t for (_cc, _nc, t, _ct, _callers) in stats.stats.values())  # type: ignore[attr-defined]
    rows = []
    for (file, line, name), (_cc, ncall, tt, ct, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        if ct >= 0.01 * total:
            rows.append((ct, tt, ncall, f"{Path(file).name}:{line}({name})"))
    print(f"under cProfile: {1e3 * total / opts.periods:.3f} ms a period; per period (ms): with callees / own / calls")
    for ct, tt, ncall, where in sorted(rows, reverse=True):
        print(f"  {1e3 * ct / opts.periods:8.3f} {1e3 * tt / opts.periods:8.3f} {ncall / opts.periods:6.1f}  {where}")
    if opts.backend == "warp":
        print(f"buffers: nconmax {sim.nconmax}, njmax {sim.njmax} per world ({'as built' if (sim.nconmax, sim.njmax) == built else f'built {built}'})")
    sim.shutdown()
    dsim.shutdown()
    return None


def probe_host(sim: batchsim.BatchedSystem, u: np.ndarray, periods: int) -> None:
    """The host's share of a period, piece by piece: what write() does to the commands (a check
    for NaN and out-of-range values, the narrowing to float32), timed on copies of the same
    arrays inside real periods (so the caches are as write() finds them), and alternatives
    that make one pass fewer: the sum of squares (one BLAS pass) for the check, np.copyto for
    the narrowing. Only public arrays are touched; the period runs after each probe."""
    c = sim.command
    flat = c.reshape(-1)
    scratch = np.empty(c.shape, np.float32)
    probes: dict[str, Callable[[], object]] = {
        "command[:] = u": lambda: np.copyto(c, u),
        "min()": c.min,
        "max()": c.max,
        "dot(c, c)": lambda: np.dot(flat, flat),
        "abs().max()": lambda: np.abs(c).max(),
        "narrow: scratch[:] = c": lambda: scratch.__setitem__(slice(None), c),
        "narrow: copyto": lambda: np.copyto(scratch, c, casting="same_kind"),
        "write()": sim.write,
        "step()": lambda: sim.step(NSTEP),
        "read()": sim.read,
    }
    times: dict[str, list[float]] = {k: [] for k in probes}
    for _ in range(periods):
        for name, probe in probes.items():
            t0 = time.perf_counter()
            probe()
            times[name].append(time.perf_counter() - t0)
    print("host pieces inside real periods, median (worst) us: " + "; ".join(
        f"{k} {1e6 * statistics.median(v):.0f} ({1e6 * max(v):.0f})" for k, v in times.items()
    ))
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?")
    print(f"# cpu {cpu}; numpy {np.__version__}; load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
