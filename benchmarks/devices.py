"""One fleet over several devices: steps/s through the contract against the sum of the raw
library on each device alone, in one run.

For each device count k (1, 2, ... up to the devices given), with `--worlds` worlds per
device, it times the contract period (`command`, `write`, `step(NSTEP)`, `read`) of one
system over the first k devices (batchsim.make(..., devices=[...])), and the raw library's
loop (benchmarks/throughput.py's, the same physics per call) on each of those devices
alone, one after the other; the ideal for k devices is the sum of those k raw figures.
It prints a scaling table (k, worlds, contract steps/s, sum of raw, ratio, contract(k) /
contract(1)) and writes devices.csv and devices.png to --out.

    python benchmarks/throughput.py --devices all --backends warp --worlds 8192 --model humanoid
    python benchmarks/devices.py --devices 0,1 --worlds 8192        # the same, directly
"""

from __future__ import annotations

import argparse
import csv
import datetime
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled
sys.path.insert(0, str(Path(__file__).resolve().parent))

from throughput import NSTEP, RAW, device_name, versions  # noqa: E402

import batchsim  # noqa: E402
from batchsim.backends import backend_class  # noqa: E402

FIELDS = [
    "date",
    "device",
    "model",
    "backend",
    "ndevice",
    "nworld",
    "contract_sps",
    "raw_sum_sps",
    "ratio",
    "scaling",
]


def measure(model: str, backend: str, devices: list, per_device: int, seconds: float) -> dict:
    """Contract over `devices` at once, and the raw loop on each device alone."""
    nworld = per_device * len(devices)
    sim = batchsim.make(model, nworld, backend, devices=devices)
    sim.configure()
    sim.activate()
    command = np.random.default_rng(0).uniform(-0.3, 0.3, sim.command.shape)

    def contract() -> None:
        sim.command[:] = command
        sim.write()
        sim.step(NSTEP)
        sim.read()

    for _ in range(3):  # compile, capture, warm up
        contract()
    c = _timed(contract, nworld, seconds)
    raw_sum = 0.0
    for shard in getattr(sim, "shards", [sim]):  # each device alone, the others idle
        ctrl = np.zeros((shard.nworld, sim.model.nu))
        ctrl[:, [a.actuator_id for a in sim.spec.commands]] = command[: shard.nworld]
        raw = RAW[backend](shard, ctrl)
        for _ in range(2):
            raw()
        raw_sum += _timed(raw, shard.nworld, seconds)
        del raw
    frozen = int((sim.status != 0).sum())
    sim.shutdown()
    return {"contract_sps": c, "raw_sum_sps": raw_sum, "ratio": c / raw_sum, "frozen": frozen}


def _timed(body, nworld: int, seconds: float) -> float:
    """Steps/s of `body` (NSTEP steps of nworld worlds per call) over about `seconds`."""
    t0 = time.perf_counter()
    calls = 0
    while time.perf_counter() - t0 < seconds:
        body()
        calls += 1
    return calls * nworld * NSTEP / (time.perf_counter() - t0)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = [int(r["ndevice"]) for r in rows]
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(k, [float(r["contract_sps"]) / 1e6 for r in rows], "o-", label="batchsim, one fleet")
    ax.plot(k, [float(r["raw_sum_sps"]) / 1e6 for r in rows], "s--", label="sum of raw, each device alone")
    ax.set_xlabel("devices")
    ax.set_ylabel("physics steps/s (millions)")
    ax.set_xticks(k)
    ax.set_title(
        f"{rows[0]['model']}, {rows[0]['nworld']} worlds per device, {rows[0]['backend']}", fontsize=9
    )
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
    p.add_argument("--out", default="benchmarks/out")
    args, _ = p.parse_known_args(argv)
    backend = args.backends.split(",")[0].strip()
    cls = backend_class(batchsim.Backend.parse(backend))
    if args.devices == "all":
        devices: list = list(cls.available_devices())
    else:
        devices = [int(d) if d.strip().isdigit() else d.strip() for d in args.devices.split(",")]
        have = cls.available_devices()
        devices = [have[d] if isinstance(d, int) else d for d in devices]
    per_device = int(args.worlds.split(",")[0])
    date = datetime.date.today().isoformat()
    device = device_name([backend])
    print(f"batchsim devices: {args.model}, {per_device} worlds per device, {NSTEP} steps per period, {date}")
    print(f"{device}\n{versions()}\ndevices: {', '.join(map(str, devices))}", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    one = None
    print(
        f"{'devices':>7} {'worlds':>7} {'batchsim steps/s':>17} {'sum of raw':>14} {'ratio':>6} {'x one device':>12}"
    )
    for k in range(1, len(devices) + 1):
        result = measure(args.model, backend, devices[:k], per_device, args.seconds)
        one = one or result["contract_sps"]
        row = {
            "date": date,
            "device": device,
            "model": args.model,
            "backend": backend,
            "ndevice": k,
            "nworld": per_device,
            "contract_sps": result["contract_sps"],
            "raw_sum_sps": result["raw_sum_sps"],
            "ratio": result["ratio"],
            "scaling": result["contract_sps"] / one,
        }
        rows.append(row)
        print(
            f"{k:7d} {k * per_device:7d} {row['contract_sps']:17,.0f} {row['raw_sum_sps']:14,.0f} "
            f"{row['ratio']:6.3f} {row['scaling']:12.2f}"
            + (f"  ({result['frozen']} worlds frozen)" if result["frozen"] else ""),
            flush=True,
        )
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
