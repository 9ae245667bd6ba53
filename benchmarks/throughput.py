"""Physics throughput through the contract against the raw libraries, per backend and world count.

For each backend and world count, in one process and interleaved in rounds so that both
sides see the same machine state, it times:

  contract: sim.write(); sim.step(NSTEP); sim.read(), with sim.command[:] = u before each
            call where the raw loop copies its commands each call too (cpu), else once
            (mjx, warp: raw sets ctrl once); write() checks and applies `command` every call
  raw:      the library itself doing the same physics, NSTEP steps per call, synchronized:
            cpu  mujoco.batch.Batch: ctrl[:] = u; batch.step(nstep=NSTEP)
            mjx  jax.jit(lax.scan over NSTEP of jax.vmap(mjx.step)), Data donated, float32
                 matrix products (batchsim's mjx asks for them; JAX's GPU default is TF32)
            warp MuJoCo Warp: NSTEP mjw.step captured in one graph, launched and synchronized
                 (Warp replays graphs on its CPU device too), same nconmax/njmax as the contract
  raw+keep (warp only): the raw loop, its graph also keeping a copy of the period's start
            (mjw.get_state of mjSTATE_PHYSICS and the warmstart, qfrc_actuator, sensordata, a
            float64 clock), as batchsim does so that an overflowing period can be repeated:
            the cost of that copy, in the same terms
  raw+keep+io (warp only): that, its graph also moving the bytes any loop that commands from
            the host moves: every world's commands up and its state down (the contract's
            float64 columns, pinned host memory), the floor under the contract's host path
  contract+copy (warp only): a second fleet whose loop also copies u into `command` each call,
            as a loop whose commands change does: the user's own pass over the commands

Both sides start from the same state, warm up for the same number of periods and make the
same number of calls per round, so they simulate the same stretch of time. It reports
physics steps/s (nworld * NSTEP / seconds; compile and graph capture excluded),
the ratio contract/raw, and which backend `auto` picks (as recorded: `--plot` keeps each
row's `auto` column, the rule of the day it was run). Writes throughput.csv and
throughput.png (steps/s vs worlds, log-log, one colour per backend, raw dashed) to --out.

    python benchmarks/throughput.py --backends cpu,mjx,warp --worlds 16,256,1024,8192 --model humanoid
    python benchmarks/throughput.py --plot a.csv b.csv --out benchmarks/results   # merge runs, redraw
    python benchmarks/throughput.py --around-threshold --model humanoid   # auto's threshold, held out
    python benchmarks/throughput.py --devices all --backends warp --worlds 8192   # several GPUs (devices.py)
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # a source checkout, uninstalled

import batchsim  # noqa: E402
from batchsim.backends import WARP_MIN_WORLDS, resolve  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raw_loops import COPIES_EACH_CALL, NSTEP, RAW, raw_warp, unequal_buffers  # noqa: E402  (the raw libraries' loops)

# --around-threshold: world counts as multiples of WARP_MIN_WORLDS (128 .. 2048 at 512)
THRESHOLD_FACTORS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 4.0)
FIELDS = [
    "date",
    "device",
    "model",
    "backend",
    "nworld",
    "nstep",
    "contract_sps",
    "raw_sps",
    "ratio",
    "auto",
    "compile_s",
    "note",
]


# ---------------------------------------------------------------- timing


def rate(body: Callable[[], None], calls: int, work: int) -> float:
    """Steps/s of `calls` calls of `body`, which does `work` physics steps per call."""
    t0 = time.perf_counter()
    for _ in range(calls):
        body()
    return calls * work / (time.perf_counter() - t0)


def interleaved(
    contract: Callable[[], None],
    raw: Callable[[], None],
    work: int,
    seconds: float,
    rounds: int = 3,
    extra: Callable[[], None] | list[Callable[[], None]] | None = None,
) -> tuple[float, float, list[float], Any]:
    """Median steps/s of contract and raw, measured in alternating rounds (who goes first
    alternates), each round's ratio contract/raw, to show the spread, and the median steps/s
    of `extra` (a variant of raw, timed after the two in each round) if given (a list of
    variants: a list of their medians).

    Both sides make the same number of calls each round, so that, having started from the
    same initial state with the same commands and the same number of warm-up periods, they
    simulate the same stretch of time: an MJX step costs more or less with the contact state
    (seen: 13% between two 256-world humanoid fleets at different moments of their fall).
    """
    t0 = time.perf_counter()
    raw()
    calls = max(3, round(seconds / rounds / (time.perf_counter() - t0)))
    contract()  # and the contract one period too: both stay in step
    extras = [] if extra is None else extra if isinstance(extra, list) else [extra]
    c, r, x = [], [], [[] for _ in extras]
    for i in range(rounds):
        if i % 2:
            c.append(rate(contract, calls, work))
            r.append(rate(raw, calls, work))
        else:
            r.append(rate(raw, calls, work))
            c.append(rate(contract, calls, work))
        for body, rates in zip(extras, x, strict=True):
            rates.append(rate(body, calls, work))
    medians = [float(np.median(v)) for v in x]
    return (
        float(np.median(c)),
        float(np.median(r)),
        [a / b for a, b in zip(c, r, strict=True)],
        medians if isinstance(extra, list) else (medians[0] if medians else None),
    )




# ---------------------------------------------------------------- one measurement


def measure(
    model: str,
    backend: str,
    nworld: int,
    seconds: float,
    rounds: int = 3,
    deterministic: bool = False,
    buffers: tuple[int, int] | None = None,
    again: bool | None = None,
) -> dict:
    """One size of one backend. warp: when the contract's buffers grew during the timing (a
    long run of falling humanoids does, at about 8 s of sim time) or raw's overflowed, the
    two stepped different physics, so it is measured again from the start, every side built
    with the grown (nconmax, njmax) (`buffers`), and the note says so (`again`: whether it may;
    by default only when no `buffers` were given)."""
    t0 = time.perf_counter()
    sizing = {} if buffers is None else {"nconmax": buffers[0], "njmax": buffers[1]}
    sim = batchsim.make(model, nworld, backend, deterministic=deterministic, **sizing)
    sim.configure()
    sim.activate()
    rng = np.random.default_rng(0)
    lo, hi = -0.3, 0.3
    command = rng.uniform(lo, hi, sim.command.shape)
    ctrl = np.zeros((nworld, sim.model.nu))
    ctrl[:, [c.actuator_id for c in sim.spec.commands]] = command

    def loop(system: batchsim.BatchedSystem, copy: bool) -> Callable[[], None]:
        def body() -> None:
            if copy:
                system.command[:] = command
            system.write()
            system.step(NSTEP)
            system.read()

        return body

    sim.command[:] = command
    contract = loop(sim, COPIES_EACH_CALL[backend])
    for _ in range(3):  # compile, capture, warm caches
        contract()
    compile_s = time.perf_counter() - t0
    built = (sim.nconmax, sim.njmax) if backend == "warp" else (0, 0)
    raw = RAW[backend](sim, ctrl)
    for _ in range(2):
        raw()
    extras = []
    if backend == "warp":
        extras = [raw_warp(sim, ctrl, keep_start=True), raw_warp(sim, ctrl, keep_start=True, io=True)]
        for body in extras:
            for _ in range(2):
                body()
        # the contract again on a fleet of its own (the same moment of the fall as the others)
        copying = batchsim.make(model, nworld, backend, deterministic=deterministic, **sizing)
        copying.configure()
        copying.activate()
        extras.append(loop(copying, True))
        for _ in range(4):  # as many periods as `contract` has run when the timing starts
            extras[-1]()
    c, r, per_round, ks = interleaved(contract, raw, nworld * NSTEP, seconds, rounds, extra=extras)
    unequal = None
    if backend == "warp":  # the raw loops (extras[:2]) overflowed, or either contract fleet grew
        unequal = unequal_buffers(sim, built, [raw, *extras[:2]]) or unequal_buffers(copying, built, [])
    if unequal is not None and (buffers is None if again is None else again):
        grown = (max(sim.nconmax, copying.nconmax), max(sim.njmax, copying.njmax))
        if grown == built:  # raw overflowed where the contract did not grow: give both room
            grown = (2 * built[0], 2 * built[1])
        sim.shutdown()
        copying.shutdown()
        del raw, extras
        second = measure(model, backend, nworld, seconds, rounds, deterministic, buffers=grown, again=False)
        second["note"] = f"measured again from the start at nconmax {grown[0]}, njmax {grown[1]}: {unequal}; " + second["note"]
        return second
    note = f"rounds {min(per_round):.2f}-{max(per_round):.2f}"
    if unequal is not None:
        note += f"; NOT THE SAME PHYSICS: {unequal}"
    if ks:
        k, kio, copied = ks
        note += f"; raw+keep {k:,.0f} steps/s: keeping the period's start costs {r / k - 1:+.1%} of a period"
        note += (
            f"; raw+keep+io {kio:,.0f} steps/s: with the bytes a host loop moves {r / kio - 1:+.1%}, "
            f"the contract at {c / kio:.3f} of that"
        )
        note += f"; contract+copy {copied:,.0f} steps/s: {copied / r:.3f} of raw with the loop's own copy of the commands"
        copying.shutdown()
    if sim.status.any():
        note += f"; {int((sim.status != 0).sum())} worlds frozen"
    if backend == "warp":
        note += f"; nconmax {sim.nconmax} njmax {sim.njmax}"
    if deterministic:
        note += "; deterministic"
    sim.shutdown()
    del raw
    return {"contract_sps": c, "raw_sps": r, "ratio": c / r, "compile_s": compile_s, "note": note}


def device_name(backends: list[str]) -> str:
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=10,
        )
        gpu = out.stdout.strip().splitlines()[0] if out.returncode == 0 and out.stdout.strip() else ""
    except (OSError, subprocess.SubprocessError):
        gpu = ""
    cpu = f"{os.cpu_count()} CPU cores ({platform.processor() or platform.machine()})"
    return f"{gpu}, {cpu}" if gpu else cpu


def versions() -> str:
    from importlib import metadata

    out = []
    for pkg in ("mujoco", "mujoco-mjx", "mujoco-warp", "warp-lang", "jax", "jaxlib"):
        try:
            out.append(f"{pkg} {metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            pass
    return ", ".join(out)


# ---------------------------------------------------------------- output


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"cpu": "tab:blue", "mjx": "tab:orange", "warp": "tab:green"}
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for backend in ("cpu", "mjx", "warp"):
        sel = sorted((r for r in rows if r["backend"] == backend), key=lambda r: int(r["nworld"]))
        if not sel:
            continue
        n = [int(r["nworld"]) for r in sel]
        ax.plot(
            n,
            [float(r["contract_sps"]) for r in sel],
            "o-",
            color=colors[backend],
            label=f"{backend} (batchsim)",
        )
        ax.plot(
            n,
            [float(r["raw_sps"]) for r in sel],
            "--",
            color=colors[backend],
            alpha=0.7,
            label=f"{backend} raw library",
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("worlds")
    ax.set_ylabel("physics steps / s")
    models = sorted({r["model"] for r in rows})
    devices = sorted({r["device"] for r in rows})
    ax.set_title(
        f"{', '.join(models)}: write + step({NSTEP}) + read per period\n{'; '.join(devices)}", fontsize=9
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def summary(rows: list[dict]) -> None:
    print(f"\n{'backend':8s} {'worlds':>7s} {'batchsim steps/s':>17s} {'raw steps/s':>13s} {'ratio':>6s}")
    for r in sorted(rows, key=lambda r: (r["backend"], int(r["nworld"]))):
        print(
            f"{r['backend']:8s} {int(r['nworld']):7d} {float(r['contract_sps']):17,.0f} "
            f"{float(r['raw_sps']):13,.0f} {float(r['ratio']):6.3f}"
        )
    sizes = sorted({int(r["nworld"]) for r in rows})
    print(f"\n{'worlds':>7s} {'auto picks':>10s} {'auto steps/s':>13s} {'fastest':>8s} {'auto/fastest':>12s}")
    for n in sizes:
        at = {r["backend"]: float(r["contract_sps"]) for r in rows if int(r["nworld"]) == n}
        auto = next(r["auto"] for r in rows if int(r["nworld"]) == n)  # as recorded
        best = max(at, key=at.get)
        if auto in at:
            print(f"{n:7d} {auto:>10s} {at[auto]:13,.0f} {best:>8s} {at[auto] / at[best]:12.3f}")
        else:
            print(f"{n:7d} {auto:>10s} {'(not run)':>13s} {best:>8s}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backends", default=None, help="default cpu,mjx,warp (cpu,warp with --around-threshold)")
    p.add_argument("--worlds", default=None, help="default 16,256,1024,8192")
    p.add_argument(
        "--around-threshold",
        action="store_true",
        help=f"only the sizes around auto's cpu/warp threshold ({WARP_MIN_WORLDS} worlds), to check the "
        "rule on data it was not fitted on; writes throughput_threshold.csv",
    )
    p.add_argument("--model", default="humanoid")
    p.add_argument("--seconds", type=float, default=1.5, help="timed seconds per side and size")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds per size (medians)")
    p.add_argument(
        "--deterministic",
        action="store_true",
        help="bitwise-repeatable mode, on both sides (the raw library configured the same way)",
    )
    p.add_argument(
        "--budget", type=float, default=None, help="stop starting new sizes after this many seconds"
    )
    p.add_argument("--out", default="benchmarks/out")
    p.add_argument("--plot", nargs="*", default=None, metavar="CSV", help="only merge these CSVs and draw")
    p.add_argument("--devices", default=None, help="all, or 0,1,...: one fleet over several devices (devices.py)")
    args = p.parse_args(argv)
    if args.devices is not None:  # the multi-device scaling run: --worlds is per device
        import devices

        return devices.main(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.plot is not None:
        rows = []
        for f in args.plot:
            with open(f) as fh:
                rows += list(csv.DictReader(fh))
        unrecorded = [r for r in rows if not r.get("auto")]
        for r in unrecorded:  # only runs made before the column existed: today's rule, said so
            gpu = "NVIDIA" in r["device"]
            r["auto"] = "warp" if gpu and int(r["nworld"]) >= WARP_MIN_WORLDS else "cpu"
        if unrecorded:
            print(f"{len(unrecorded)} rows had no auto column: filled in with today's rule ({WARP_MIN_WORLDS} worlds)")
        summary(rows)
        plot(rows, out / "throughput.png")
        return 0

    if args.backends is None:
        args.backends = "cpu,warp" if args.around_threshold else "cpu,mjx,warp"
    if args.worlds is None:
        args.worlds = (
            ",".join(str(int(WARP_MIN_WORLDS * f)) for f in THRESHOLD_FACTORS)
            if args.around_threshold
            else "16,256,1024,8192"
        )
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    sizes = [int(n) for n in args.worlds.split(",")]
    device = device_name(backends)
    date = datetime.date.today().isoformat()
    print(
        f"batchsim throughput: {args.model}, {NSTEP} steps per period, {date}\n{device}\n{versions()}",
        flush=True,
    )
    spec = batchsim.load(args.model)
    start = time.perf_counter()
    rows = []
    csv_path = out / ("throughput_threshold.csv" if args.around_threshold else "throughput.csv")
    with open(csv_path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, FIELDS)
        writer.writeheader()
        for backend in backends:
            for n in sizes:
                if args.budget is not None and time.perf_counter() - start > args.budget:
                    print(f"{backend} {n}: skipped, over the --budget", flush=True)
                    continue
                auto = resolve("auto", spec, n)[0].value
                try:
                    result = measure(args.model, backend, n, args.seconds, args.rounds, args.deterministic)
                except Exception as e:  # one failed size must not lose the others
                    print(f"{backend} {n}: FAILED {type(e).__name__}: {e}", flush=True)
                    continue
                row = {
                    "date": date,
                    "device": device,
                    "model": args.model,
                    "backend": backend,
                    "nworld": n,
                    "nstep": NSTEP,
                    "auto": auto,
                    **result,
                }
                rows.append(row)
                writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
                fh.flush()
                print(
                    f"{backend:5s} {n:6d} worlds: batchsim {result['contract_sps']:13,.0f} steps/s, raw "
                    f"{result['raw_sps']:13,.0f}, ratio {result['ratio']:.3f}, setup {result['compile_s']:.1f} s"
                    f" {result['note']}",
                    flush=True,
                )
    print(f"wrote {csv_path}")
    if rows:
        summary(rows)
        try:
            plot(rows, csv_path.with_suffix(".png"))
        except ImportError:
            print("matplotlib is not installed: no plot (pip install 'batchsim[bench]')")
    return 0


if __name__ == "__main__":
    sys.exit(main())
