"""What the controllers cost per control period, message hand-over included, against the physics.

Every control period runs, in one process, on the cpu backend (or `--backend warp|mjx` on a
GPU host), as the loop runs it:

  hand-over:    what arrived in this period, one call per controller, as a bridge delivers it
                (`set_cmd_vel_batch`, `set_commands_batch`)
  controllers:  manager.update(sim, t, period)           (the model's default YAML)
  physics:      sim.write(); sim.step(substeps, meanwhile=...); sim.read()

Trajectories (`set_trajectories(batch)`: validation and queueing) are handed over as the bridge
hands them (ros_bridge/trajectory_inputs.py): in step()'s `meanwhile`, while the device steps
(on the cpu backend, just before the steps), and they start at the next period's update. Then,
as SimLoop calls it there too, the manager's `while_stepping` makes ahead what the next update
needs (the segments the worlds enter). Both count in the physics' column only where they outlast
the device's steps; their own times are reported apart.

The controllers' share of a period is hand-over + update, timed together; the physics is
timed apart. Both, and the whole period (their sum, what a control period's deadline
holds), are reported as the median and the worst period (and the 99th percentile, since
one stray period of a shared machine sets the worst). `--clock cpu`
times the controllers by this process's CPU time instead of the wall clock: on a machine
whose cores other jobs share, that leaves out the time the process waited for a core
(the controllers run in one thread; the physics column stays wall time).

Cases:
  arm stream  each world re-sends a 10-point cubic trajectory every 0.2 s, staggered, so
              about nworld/20 trajectories start in each period
  arm burst   every world gets a new 10-point trajectory in the same period, every 0.2 s
  arm long    16 worlds only: as stream, and world 0 gets a 10,000-point trajectory every 0.5 s
  car         every world gets a cmd_vel every 0.1 s, all in the same period
  quadruped   every world gets an effort command every 0.1 s, all in the same period

The first 0.4 s of sim time (two rounds of trajectories) are a warm-up and not recorded;
then at least three rounds (three bursts) and `--seconds` are.
A last line times the hand-over alone: 1024 10-point trajectories in one `set_trajectories`
call, and as 1024 `set_trajectory` calls (one per message, as a bridge without batches does).

    python benchmarks/controllers.py [--worlds 16,256,1024] [--models arm,car,quadruped]
                                     [--cases stream,burst,long] [--seconds 3] [--backend cpu]
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import resource
import time
from collections.abc import Callable

import mujoco
import numpy as np

import batchsim
from batchsim.controllers import TrajectoryBatch, default_controllers, load_controllers

NPOINT = 10
RESEND = 0.2  # s of sim time between two trajectories to one world
WARMUP = 0.4  # s of sim time not recorded
LONG_NPOINT = 10_000
LONG_RESEND = 0.5


def trajectories(
    jtc, worlds: np.ndarray, npoint: int, span: float, rng: np.random.Generator
) -> TrajectoryBatch:
    """A batch of cubic trajectories, `npoint` points over `span` seconds, one per world."""
    n, nj = len(worlds), len(jtc.joints)
    times = np.tile(np.linspace(span / npoint, span, npoint), n)
    positions = rng.uniform(-0.3, 0.3, (n * npoint, nj))
    return TrajectoryBatch(
        worlds=np.asarray(worlds, np.int64),
        start_time=np.zeros(n),
        joint_mask=np.ones((n, nj), bool),
        offsets=np.arange(n + 1, dtype=np.int64) * npoint,
        times=times,
        positions=positions,
        velocities=np.zeros_like(positions),
        has_velocities=np.ones(n, bool),
    )


def merge(a: TrajectoryBatch, b: TrajectoryBatch) -> TrajectoryBatch:
    """One batch holding a's trajectories, then b's."""
    return TrajectoryBatch(
        worlds=np.concatenate([a.worlds, b.worlds]),
        start_time=np.concatenate([a.start_time, b.start_time]),
        joint_mask=np.concatenate([a.joint_mask, b.joint_mask]),
        offsets=np.concatenate([a.offsets, a.offsets[-1] + b.offsets[1:]]),
        times=np.concatenate([a.times, b.times]),
        positions=np.concatenate([a.positions, b.positions]),
        velocities=np.concatenate([a.velocities, b.velocities]),
        has_velocities=np.concatenate([a.has_velocities, b.has_velocities]),
    )


def feeder(
    model: str, case: str, manager, nworld: int, period: float
) -> Callable[[int], Callable[[], None] | None]:
    """For period k, the hand-over to run in it (None: nothing arrived); messages are built beforehand."""
    rng = np.random.default_rng(0)
    every = round(RESEND / period)
    if model == "arm":
        jtc = manager["joint_trajectory_controller"]
        streaming = np.arange(1 if case == "long" else 0, nworld)

        def arrivals(k: int) -> Callable[[], None] | None:
            if case == "burst":
                worlds = streaming if k % every == 0 else streaming[:0]
            else:  # staggered: world w re-sends in the periods k with k % every == w % every
                worlds = streaming[streaming % every == k % every]
            batch = trajectories(jtc, worlds, NPOINT, RESEND + 0.05, rng) if len(worlds) else None
            if case == "long" and k % round(LONG_RESEND / period) == 0:
                long = trajectories(jtc, np.array([0]), LONG_NPOINT, 100.0, rng)
                batch = long if batch is None else merge(batch, long)
            if batch is None:
                return None

            def handover() -> None:
                rejected = jtc.set_trajectories(batch)
                assert not rejected, rejected

            return handover

        return arrivals

    worlds = np.arange(nworld)
    if model == "car":
        dd = manager["diff_drive_controller"]
        rows = np.tile([0.3, 0.2], (nworld, 1))

        def handover() -> None:
            assert not dd.set_cmd_vel_batch(worlds, rows)

    else:
        fcc = manager["effort_controller"]
        rows = np.zeros((nworld, len(fcc.joints)))

        def handover() -> None:
            assert not fcc.set_commands_batch(worlds, rows)

    every = round(0.1 / period)
    return lambda k: handover if k % every == 0 else None


def thread_usage() -> np.ndarray:
    """This thread's CPU seconds, involuntary context switches (the kernel gave its core to
    another thread), minor and major page faults so far: a period's difference says whether a
    stray period computed, faulted, or waited. The CPU seconds are the thread's clock
    (CLOCK_THREAD_CPUTIME_ID, nanoseconds; getrusage's counted 4 ms ticks on the GPU hosts),
    which on a VM whose kernel accounts steal (CONFIG_PARAVIRT_TIME_ACCOUNTING, the GPU hosts')
    leaves out the time the hypervisor ran something else on the core."""
    r = resource.getrusage(resource.RUSAGE_THREAD)
    return np.array([time.thread_time(), r.ru_nivcsw, r.ru_minflt, r.ru_majflt])


def steal_seconds() -> float:
    """Seconds every core of this VM has had stolen by its hypervisor so far (/proc/stat's
    steal column, summed; 0 where there is none or no /proc)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


class GcClock:
    """The collector's time, as gc.callbacks report it: seconds so far, and the oldest generation
    collected since `take()` (-1: none), so that a stray period can be told apart as a collection."""

    def __init__(self) -> None:
        self.seconds, self.oldest, self._start = 0.0, -1, 0.0
        gc.callbacks.append(self)

    def __call__(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._start = time.perf_counter()
        else:
            self.seconds += time.perf_counter() - self._start
            self.oldest = max(self.oldest, int(info["generation"]))

    def take(self) -> tuple[float, int]:
        out = (self.seconds, self.oldest)
        self.seconds, self.oldest = 0.0, -1
        return out

    def close(self) -> None:
        gc.callbacks.remove(self)


def measure(
    model: str,
    case: str,
    nworld: int,
    seconds: float,
    clock: Callable[[], float] = time.perf_counter,
    backend: str = "cpu",
) -> dict[str, np.ndarray]:
    """Seconds per period of the physics and of the controllers (hand-over + update), recorded
    periods only (the warm-up's first period compiles on the GPU backends)."""
    sim = batchsim.make(model, nworld, backend)
    sim.configure()
    sim.activate()
    manager = load_controllers(default_controllers(model), sim.spec, nworld)
    rate = manager.update_rate or 100.0
    substeps = max(1, round(1.0 / (rate * sim.dt)))
    period = substeps * sim.dt
    arrivals = feeder(model, case, manager, nworld, period)
    warmup = round(WARMUP / period)
    least = warmup + 3 * round(max(RESEND, LONG_RESEND if case == "long" else 0) / period)
    physics_t, control_t, arrived, usage, control_cpu, handover_t, beside_t, ahead_t = [], [], [], [], [], [], [], []
    buffers = (getattr(sim, "nconmax", None), getattr(sim, "njmax", None))  # warp's, to see them grow
    gc.collect()
    gc.freeze()  # start-up's objects out of the collector, as the paced loop does (SimLoop)
    stolen = steal_seconds()
    collector = GcClock()
    collected = []
    wall = time.perf_counter()
    k, t = 0, 0.0  # sim time as SimLoop keeps it (+= period): prepare's t + period is the next update's time
    while k < least or time.perf_counter() - wall < seconds:
        handover = arrivals(k)
        beside = handover if model == "arm" else None  # trajectories: while the device steps, as the bridge
        u0 = thread_usage()
        collector.take()
        s = clock()
        if handover is not None and beside is None:
            handover()
        h = clock()
        manager.update(sim, t, period)
        c = clock()
        c_cpu = time.thread_time()
        p = time.perf_counter()
        sim.write()
        took = [0.0, 0.0]

        def meanwhile(beside: Callable[[], None] | None = beside, took: list[float] = took, t: float = t) -> None:
            b = time.perf_counter()
            if beside is not None:  # the bridge's while_stepping, then the manager's (SimLoop's order)
                beside()
            m = time.perf_counter()
            manager.while_stepping(sim, t, period)
            took[0], took[1] = m - b, time.perf_counter() - m

        sim.step(substeps, meanwhile=meanwhile)
        sim.read()
        e = time.perf_counter()
        if k >= warmup:
            control_t.append(c - s)
            physics_t.append(e - p)
            arrived.append(handover is not None)
            usage.append(thread_usage() - u0)
            control_cpu.append(c_cpu - u0[0])
            handover_t.append(h - s)
            beside_t.append(took[0])
            ahead_t.append(took[1])
            collected.append(collector.take())
        k += 1
        t += period
    out_wall = time.perf_counter() - wall
    collector.close()
    stolen = steal_seconds() - stolen
    grown = (getattr(sim, "nconmax", None), getattr(sim, "njmax", None))
    sim.shutdown()
    gc.unfreeze()
    out = {"physics": np.array(physics_t), "controllers": np.array(control_t), "arrived": np.array(arrived)}
    out["handover"] = np.array(handover_t)  # the controllers' time: hand-over, then the update
    out["beside"] = np.array(beside_t)  # the trajectories' hand-over, in the physics' time (while the device steps)
    out["ahead"] = np.array(ahead_t)  # the controllers' work done ahead for the next update (while the device steps)
    out["control_cpu"] = np.array(control_cpu)  # the controllers' part of it on a core (thread clock)
    out["usage"] = np.array(usage).reshape(-1, 4)  # per period: on-CPU s, involuntary switches, minor and major faults
    out["steal"] = np.array([stolen / out_wall / (os.cpu_count() or 1)])  # the hypervisor's share of a core, on average
    out["buffers"] = np.array([buffers, grown], dtype=object)  # (nconmax, njmax) before and after
    out["gc"] = np.array(collected).reshape(-1, 2)  # per period: the collector's seconds, oldest generation (-1 none)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", default="arm,car,quadruped")
    p.add_argument("--worlds", default="16,256,1024")
    p.add_argument("--cases", default="stream,burst,long", help="the arm's cases")
    p.add_argument("--seconds", type=float, default=3.0, help="wall seconds per (case, worlds), at least")
    p.add_argument("--no-handover", action="store_true", help="skip the hand-over line")
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall", help="how the controllers are timed")
    p.add_argument("--backend", default="cpu", help="the physics' backend (cpu, warp, mjx)")
    args = p.parse_args()
    clock = time.perf_counter if args.clock == "wall" else time.process_time

    print(
        f"# {platform.node()} | {os.cpu_count()} cores | {platform.processor() or platform.machine()} | "
        f"python {platform.python_version()} | mujoco {mujoco.__version__} | numpy {np.__version__} | "
        f"{time.strftime('%Y-%m-%d')} | load {os.getloadavg()[0]:.1f} | controllers timed by {args.clock} clock | "
        f"backend {args.backend}"
    )
    print(
        f"{'model':10s} {'case':7s} {'worlds':>6s} {'periods':>7s} | {'physics ms: median':>18s} {'worst':>7s} | "
        f"{'controllers ms: median':>22s} {'p99':>7s} {'worst':>7s} | {'median ratio':>12s} | "
        f"{'period ms: median':>17s} {'worst':>7s}"
    )
    for model in args.models.split(","):
        cases = args.cases.split(",") if model == "arm" else ["-"]
        for case in cases:
            for nworld in (int(n) for n in args.worlds.split(",")):
                if case == "long" and nworld != 16:
                    continue
                r = measure(model, case, nworld, args.seconds, clock, args.backend)
                ph, ct = r["physics"] * 1e3, r["controllers"] * 1e3
                whole = ph + ct
                print(
                    f"{model:10s} {case:7s} {nworld:6d} {len(ct):7d} | {np.median(ph):18.3f} {ph.max():7.2f} | "
                    f"{np.median(ct):22.3f} {np.percentile(ct, 99):7.3f} {ct.max():7.3f} | "
                    f"{np.median(ct) / np.median(ph):12.3f} | {np.median(whole):17.3f} {whole.max():7.2f}",
                    flush=True,
                )
                # what the worst whole period was made of: a stray one of a shared machine, the
                # physics (warp's buffers growing: a period repeated), or the controllers' burst
                i = int(np.argmax(whole))
                (c0, j0), (c1, j1) = r["buffers"]
                cpu, switches, minor, major = r["usage"][i]
                print(
                    f"#   worst period: {i} of {len(whole)}, physics {ph[i]:.2f} ms, controllers {ct[i]:.2f} ms "
                    f"(hand-over {r['handover'][i] * 1e3:.2f}, update {ct[i] - r['handover'][i] * 1e3:.2f}), "
                    f"{'messages arrived' if r['arrived'][i] else 'no messages'}"
                    + (f" (trajectories handed over beside its steps {r['beside'][i] * 1e3:.2f} ms)" if r["beside"][i] else "")
                    + (", trajectories started" if model == "arm" and i and r["arrived"][i - 1] else "")
                    + "; the loop's thread in it: on a core "
                    f"{cpu * 1e3:.2f} ms (the controllers' part {r['control_cpu'][i] * 1e3:.2f}), {switches:.0f} involuntary switches, {minor:.0f} minor and {major:.0f} major "
                    f"page faults (median period: on a core {np.median(r['usage'][:, 0]) * 1e3:.2f} ms, "
                    f"{np.median(r['usage'][:, 2]):.0f} minor faults; steal over the run {r['steal'][0]:.1%} of each core); "
                    f"periods over 2x the median "
                    f"{int((whole > 2 * np.median(whole)).sum())}; "
                    f"the collector in it {r['gc'][i, 0] * 1e3:.2f} ms{gc_generation(r['gc'][i, 1])}, over the run "
                    f"{int((r['gc'][:, 1] == 2).sum())} full collections, longest {r['gc'][:, 0].max() * 1e3:.2f} ms"
                    + (f"; warp buffers nconmax {c0} -> {c1}, njmax {j0} -> {j1}" if c0 is not None else ""),
                    flush=True,
                )
                if model == "arm" and r["arrived"].any():
                    starts = np.flatnonzero(r["arrived"][:-1]) + 1  # the periods whose update starts them
                    b = r["beside"][r["arrived"]] * 1e3
                    a = r["ahead"] * 1e3
                    print(
                        f"#   made ahead beside the steps: median {np.median(a):.2f} ms, worst {a.max():.2f}; "
                        f"trajectories: handed over beside the steps in {len(b)} periods, median {np.median(b):.2f} ms, "
                        f"worst {b.max():.2f}; the {len(starts)} periods that start them: controllers median "
                        f"{np.median(ct[starts]):.2f}, worst {ct[starts].max():.2f} ms; whole period median "
                        f"{np.median(whole[starts]):.2f}, worst {whole[starts].max():.2f} ms",
                        flush=True,
                    )
    if not args.no_handover:
        one, each = handover(1024, clock)
        print(
            f"hand-over of 1024 10-point trajectories, median of 20: one set_trajectories call {one * 1e3:.2f} ms, "
            f"1024 set_trajectory calls {each * 1e3:.2f} ms"
        )


def gc_generation(oldest: float) -> str:
    return "" if oldest < 0 else f" (generation {int(oldest)})"


def handover(nworld: int, clock: Callable[[], float] = time.perf_counter) -> tuple[float, float]:
    """Median seconds to hand `nworld` trajectories over in one batch, and one call per trajectory."""
    spec = batchsim.load("arm")
    jtc = load_controllers(default_controllers("arm"), spec, nworld)["joint_trajectory_controller"]
    rng = np.random.default_rng(1)
    batched, single = [], []
    for _ in range(20):
        batch = trajectories(jtc, np.arange(nworld), NPOINT, RESEND + 0.05, rng)
        s = clock()
        jtc.set_trajectories(batch)
        batched.append(clock() - s)
        names, lo = jtc.joints, batch.offsets
        s = clock()
        for k in range(nworld):
            rows = slice(lo[k], lo[k + 1])
            jtc.set_trajectory(k, names, batch.times[rows], batch.positions[rows], batch.velocities[rows])
        single.append(clock() - s)
    return float(np.median(batched)), float(np.median(single))


if __name__ == "__main__":
    main()
