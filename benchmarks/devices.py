"""One fleet over several devices: steps/s through the contract against the sum of the raw
library on each device alone, in one run.

First the raw library's loop (benchmarks/throughput.py's, the same physics per call) on each
device alone, one after the other: the ideal for k devices is the sum of k of those. Then,
for each device count k (1, 2, ... up to the devices given), with `--worlds` worlds per
device, the contract period (`command`, `write`, `step(NSTEP)`, `read`) of one system over
the first k devices (batchsim.make(..., devices=[...])), with the shards in processes and
in threads (`--shards`). It prints a scaling table (k, shards, worlds, contract steps/s, sum
of raw, ratio, contract(k) / contract(1), the period's median and worst) and writes
devices.csv and devices.png to --out. Beside the sum of raw, "raw at once" is the raw loop
run on the k devices at the same time, one process each: what the devices give together.

The period's parts are timed apart: `set`, the period's commands put in (`--commands set`:
`sim.command = ...`, set_command, which a fleet copies on as many threads as shards where
cores allow; `assign`: `sim.command[:] = ...`, one copy in this process), then `write`,
`step`, `read` (up to 2026-11-26 the `write` column held the commands' copy too). With shard
processes a line under each row says, per call, when the request had reached the last shard,
when the last shard was done and when the fleet's call returned (us from the call's start).

    python benchmarks/throughput.py --devices all --backends warp --worlds 8192 --model humanoid
    python benchmarks/devices.py --devices 0,1 --worlds 8192        # the same, directly
"""

from __future__ import annotations

import argparse
import csv
import datetime
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled
sys.path.insert(0, str(Path(__file__).resolve().parent))

from raw_loops import NSTEP, RAW  # noqa: E402
from throughput import device_name, versions  # noqa: E402

import batchsim  # noqa: E402
from batchsim.backends import backend_class  # noqa: E402
from batchsim.backends.sharded import ShardedSystem  # noqa: E402

FIELDS = [
    "date",
    "device",
    "model",
    "backend",
    "shards",
    "ndevice",
    "nworld",
    "contract_sps",
    "raw_sum_sps",
    "ratio",
    "scaling",
    "period_median_ms",
    "period_worst_ms",
    "raw_together_sps",
    "ratio_together",
    "commands",
    "set_ms",
    "write_ms",
    "step_ms",
    "read_ms",
]
SHARDS = ("processes", "pinned", "threads")  # pinned: processes, each on cores of its own
OPS = ("write", "step", "read")


def contract(
    model: str, backend: str, devices: list, per_device: int, seconds: float, shards: str, commands: str = "set"
) -> dict:
    """Steps/s of the contract period over `devices` at once, and its median / worst period;
    `commands`: how the period's commands go in (set: sim.command = ..., assign: sim.command[:] = ...)."""
    nworld = per_device * len(devices)
    if len(devices) == 1:
        sim = batchsim.make(model, nworld, backend, device=devices[0])
    else:
        cls = backend_class(batchsim.Backend.parse(backend))
        spec = batchsim.load(model)
        processes = shards in ("processes", "pinned")
        sim = ShardedSystem(cls, spec, nworld, devices, processes=processes, pin=shards == "pinned")
        sim.initialize()
    sim.configure()
    sim.activate()
    command = _command(sim, nworld)

    parts: list[tuple[float, ...]] = []  # set, write, step, read: where a period goes
    busy: list[tuple[float, ...]] = []  # the slowest shard process's own work in write, step, read
    reach: list[tuple[float, ...]] = []  # per call: last shard began, last shard done, call back (from its start)
    shards_busy = [getattr(s, "busy", None) is not None for s in getattr(sim, "shards", [])]
    processes = bool(shards_busy) and all(shards_busy)

    def slowest() -> float:
        return max(s.busy for s in sim.shards)

    def timeline(start: float, end: float) -> tuple[float, float, float]:
        began = max(s.began for s in sim.shards)
        return began - start, max(s.began + s.busy for s in sim.shards) - start, end - start

    def period() -> None:
        t0 = time.perf_counter()
        if commands == "set":
            sim.command = command
        else:
            sim.command[:] = command
        t1 = time.perf_counter()
        sim.write()
        t2 = time.perf_counter()
        b1, r1 = (slowest(), timeline(t1, t2)) if processes else (0.0, ())
        sim.step(NSTEP)
        t3 = time.perf_counter()
        b2, r2 = (slowest(), timeline(t2, t3)) if processes else (0.0, ())
        sim.read()
        t4 = time.perf_counter()
        parts.append((t1 - t0, t2 - t1, t3 - t2, t4 - t3))
        if processes:
            busy.append((b1, b2, slowest()))
            reach.append((*r1, *r2, *timeline(t3, t4)))

    for _ in range(3):  # compile, capture, warm up
        period()
    parts.clear()
    busy.clear()
    reach.clear()
    sps, periods = _timed(period, nworld, seconds)
    frozen = int((sim.status != 0).sum())
    sim.shutdown()
    split = np.median(np.array(parts), axis=0) * 1e3
    return {
        "sps": sps,
        "median": float(np.median(periods)),
        "worst": float(np.max(periods)),
        "frozen": frozen,
        "split": split,
        "busy": np.median(np.array(busy), axis=0) * 1e3 if processes else None,
        "reach": np.median(np.array(reach), axis=0) * 1e6 if processes else None,
    }


def raw_alone(model: str, backend: str, device: str, per_device: int, seconds: float) -> float:
    """Steps/s of the raw library's loop (throughput.py's) on `device` alone, the same
    physics per call as the contract's period, sized as batchsim sizes that device's shard."""
    sim, raw = _raw_loop(model, backend, device, per_device)
    sps, _ = _timed(raw, per_device, seconds)
    del raw
    sim.shutdown()
    return sps


def _raw_loop(model: str, backend: str, device: str, per_device: int) -> tuple[batchsim.BatchedSystem, Any]:
    """A configured system on `device` (for its model and sizes) and the raw loop beside it, warmed up."""
    sim = batchsim.make(model, per_device, backend, device=device)
    sim.configure()
    ctrl = np.zeros((per_device, sim.model.nu))
    ctrl[:, [a.actuator_id for a in sim.spec.commands]] = _command(sim, per_device)
    raw = RAW[backend](sim, ctrl)
    for _ in range(2):
        raw()
    return sim, raw


def raw_together(model: str, backend: str, devices: list, per_device: int, seconds: float) -> list[float]:
    """Steps/s of the raw loop on each of `devices` at once, one process per device (each
    seeing only its own GPU, as batchsim's shard processes do), timed over the same window:
    what the devices give together, beside the sum of what each gives alone."""
    from batchsim.backends.sharded.shards import device_env

    procs = []
    for d in devices:
        env, local = device_env(str(d))
        argv = [sys.executable, __file__, "--raw-worker", local, "--backends", backend, "--model", model]
        argv += ["--worlds", str(per_device), "--seconds", str(seconds)]
        procs.append(subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env))
    try:
        for proc in procs:  # built, compiled, warmed up
            line = proc.stdout.readline()
            if line.strip() != "ready":
                raise RuntimeError(f"a raw worker failed to start: {line.strip() or proc.wait()}")
        for proc in procs:
            proc.stdin.write("go\n")
            proc.stdin.flush()
        return [float(proc.stdout.readline()) for proc in procs]
    finally:
        for proc in procs:
            proc.stdin.close()
            proc.wait()


def _raw_worker(model: str, backend: str, device: str, per_device: int, seconds: float) -> None:
    """raw_together's process: the raw loop on `device`, timed once the parent says go."""
    _, raw = _raw_loop(model, backend, device, per_device)
    print("ready", flush=True)
    sys.stdin.readline()
    sps, _ = _timed(raw, per_device, seconds)
    print(sps, flush=True)


def _command(sim: batchsim.BatchedSystem, nworld: int) -> np.ndarray:
    return np.random.default_rng(0).uniform(-0.3, 0.3, (nworld, len(sim.spec.commands)))


def _timed(body, nworld: int, seconds: float) -> tuple[float, list[float]]:
    """Steps/s of `body` (NSTEP steps of nworld worlds per call) over about `seconds`, and
    each call's duration in ms."""
    periods = []
    t0 = time.perf_counter()
    while (start := time.perf_counter()) - t0 < seconds:
        body()
        periods.append((time.perf_counter() - start) * 1e3)
    return len(periods) * nworld * NSTEP / (time.perf_counter() - t0), periods


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6))
    one = [r for r in rows if r["ndevice"] == 1]
    for shards, style in zip(SHARDS, ("o-", "v-", "^-"), strict=True):
        mine = one + [r for r in rows if r["shards"] == shards and r["ndevice"] > 1]
        if len(mine) > len(one):
            ax.plot(
                [r["ndevice"] for r in mine], [r["contract_sps"] / 1e6 for r in mine], style, label=f"batchsim, {shards}"
            )
    raw = one + [r for r in rows if r["shards"] == rows[-1]["shards"] and r["ndevice"] > 1]
    ax.plot([r["ndevice"] for r in raw], [r["raw_sum_sps"] / 1e6 for r in raw], "s--", label="sum of raw, each device alone")
    k = sorted({r["ndevice"] for r in rows})
    ax.set_xlabel("devices")
    ax.set_ylabel("physics steps/s (millions)")
    ax.set_xticks(k)
    ax.set_title(f"{rows[0]['model']}, {rows[0]['nworld']} worlds per device, {rows[0]['backend']}", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", default="all", help="'all' or device indices (0,1) or names (cpu,cpu)")
    p.add_argument("--backends", default="warp", help="one device backend: warp or mjx")
    p.add_argument("--worlds", default="8192", help="worlds per device")
    p.add_argument("--model", default="humanoid")
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--shards", default=",".join(SHARDS), help="processes, threads, or both (default)")
    p.add_argument("--counts", default="", help="device counts to run, e.g. 1,2,4 (default: 1 up to every device)")
    p.add_argument(
        "--commands", default="set", help="the commands put in by set (sim.command = ...), assign ([:] =) or both"
    )
    p.add_argument("--out", default="benchmarks/out")
    p.add_argument("--raw-worker", default=None, help=argparse.SUPPRESS)
    args, _ = p.parse_known_args(argv)
    backend = args.backends.split(",")[0].strip()
    if args.raw_worker is not None:
        _raw_worker(args.model, backend, args.raw_worker, int(args.worlds), args.seconds)
        return 0
    cls = backend_class(batchsim.Backend.parse(backend))
    if args.devices == "all":
        devices: list = list(cls.available_devices())
    else:
        devices = [int(d) if d.strip().isdigit() else d.strip() for d in args.devices.split(",")]
        have = cls.available_devices()
        devices = [have[d] if isinstance(d, int) else d for d in devices]
    per_device = int(args.worlds.split(",")[0])
    counts = [int(k) for k in args.counts.split(",") if k.strip()] or list(range(1, len(devices) + 1))
    counts = sorted({1, *(k for k in counts if 1 <= k <= len(devices))})  # one device: the baseline
    modes = [m.strip() for m in args.shards.split(",") if m.strip()]
    puts = [m.strip() for m in args.commands.split(",") if m.strip()]
    if not puts or set(puts) - {"set", "assign"}:
        p.error(f"--commands takes set, assign or both, got {args.commands!r}")
    date = datetime.date.today().isoformat()
    device = device_name([backend])
    print(f"batchsim devices: {args.model}, {per_device} worlds per device, {NSTEP} steps per period, {date}")
    print(f"{device}\n{versions()}\ndevices: {', '.join(map(str, devices))}", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # the raw library on each device alone, once: the ideal for k devices is the sum of k
    raw = [raw_alone(args.model, backend, d, per_device, args.seconds) for d in devices]
    print(f"raw, each device alone: {', '.join(f'{r:,.0f}' for r in raw)} steps/s", flush=True)
    # and all at once: whether the devices themselves give the sum when they run together
    together = {1: raw[0]}
    for k in counts[1:]:
        each = raw_together(args.model, backend, devices[:k], per_device, args.seconds)
        together[k] = sum(each)
        print(f"raw, {k} devices at once: {', '.join(f'{r:,.0f}' for r in each)} = {together[k]:,.0f} steps/s", flush=True)
    print(
        f"{'devices':>7} {'shards':>9} {'worlds':>7} {'batchsim steps/s':>17} {'sum of raw':>14} {'ratio':>6} "
        f"{'x one device':>12} {'period median / worst ms':>25} {'raw at once':>12} {'ratio':>6} "
        f"{'set / write / step / read ms':>29} {'write / step / read in the shards':>34}"
    )
    rows = []
    one = None
    for k in counts:
        for shards, put in [(m, c) for m in modes for c in puts] if k > 1 else [("-", puts[0])]:
            result = contract(args.model, backend, devices[:k], per_device, args.seconds, shards, put)
            one = one or result["sps"]
            row = {
                "date": date,
                "device": device,
                "model": args.model,
                "backend": backend,
                "shards": shards,
                "ndevice": k,
                "nworld": per_device,
                "contract_sps": result["sps"],
                "raw_sum_sps": sum(raw[:k]),
                "ratio": result["sps"] / sum(raw[:k]),
                "scaling": result["sps"] / one,
                "period_median_ms": result["median"],
                "period_worst_ms": result["worst"],
                "raw_together_sps": together[k],
                "ratio_together": result["sps"] / together[k],
                "commands": put,
                **{f"{part}_ms": float(t) for part, t in zip(("set", *OPS), result["split"], strict=True)},
            }
            rows.append(row)
            label = shards if k == 1 or len(puts) == 1 else f"{shards}/{put}"
            print(
                f"{k:7d} {label:>9} {k * per_device:7d} {row['contract_sps']:17,.0f} {row['raw_sum_sps']:14,.0f} "
                f"{row['ratio']:6.3f} {row['scaling']:12.2f} {result['median']:12.2f} / {result['worst']:9.2f} "
                f"{together[k]:12,.0f} {row['ratio_together']:6.3f} "
                f"{' / '.join(f'{t:.2f}' for t in result['split']):>29} "
                + (f"{' / '.join(f'{t:.2f}' for t in result['busy']):>34}" if result["busy"] is not None else "")
                + (f"  ({result['frozen']} worlds frozen)" if result["frozen"] else ""),
                flush=True,
            )
            if result["reach"] is not None:  # where the fleet's wait goes, us from each call's start
                r = result["reach"]
                calls = ", ".join(f"{op} " + " / ".join(f"{t:.0f}" for t in r[3 * i : 3 * i + 3]) for i, op in enumerate(OPS))
                print(f"{'':9}us after the call: request at the last shard / last shard done / back: {calls}")
    with open(out / "devices.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, FIELDS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    try:
        plot(rows, out / "devices.png")
    except ImportError:
        print("matplotlib is not installed: no plot")
    print(f"wrote {out / 'devices.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
