"""What the controllers add per control period, against the physics of that period (cpu backend).

For each model and world count, in one process, interleaved:

  physics:      sim.write(); sim.step(substeps); sim.read()      (one control period)
  controllers:  manager.update(sim, t, period)                   (the model's default YAML)

Every world is kept busy: the arm's trajectory controller always has a trajectory of
NPOINT cubic points in flight (re-sent before it ends), the car is driven by cmd_vel, the
quadruped's effort controller gets a command each period. Times are medians per period;
the last line checks the issue's bar: the trajectory controller over 1024 arms costs less
than the physics it controls.

    python benchmarks/controllers.py [--worlds 16,256,1024] [--models arm,car,quadruped] [--seconds 2]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import mujoco
import numpy as np

import batchsim
from batchsim.controllers import build as build_controllers
from batchsim.controllers import default_controllers, load_controllers, parse

NPOINT = 10


def median_time(body, seconds: float) -> float:
    """Median seconds per call of body over about `seconds`, after a warm-up."""
    for _ in range(3):
        body()
    samples = []
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline or len(samples) < 7:
        t0 = time.perf_counter()
        body()
        samples.append(time.perf_counter() - t0)
    return float(np.median(samples))


def setup(model: str, nworld: int, only: str | None):
    sim = batchsim.make(model, nworld, "cpu")
    sim.configure()
    sim.activate()
    config = parse(default_controllers(model))
    if only:
        config.controllers = [c for c in config.controllers if c.type == only]
    manager = build_controllers(config, sim.spec, nworld)
    rate = manager.update_rate or 100.0
    substeps = max(1, round(1.0 / (rate * sim.dt)))
    return sim, manager, substeps, substeps * sim.dt


def feeder(model: str, manager, nworld: int, rng: np.random.Generator):
    """A function of the loop time that keeps every world's controller busy."""
    if model == "arm":
        jtc = manager["joint_trajectory_controller"]
        names = jtc.joints
        times = np.linspace(0.1, 1.0, NPOINT)
        span = {"until": -1.0}

        def feed(t: float) -> None:
            if t < span["until"]:
                return
            for w in range(nworld):  # messages arrive per world, as from ROS
                p = rng.uniform(-0.3, 0.3, (NPOINT, len(names)))
                jtc.set_trajectory(w, names, times, p, np.zeros_like(p))
            span["until"] = t + 0.9

        return feed
    if model == "car":
        dd = manager["diff_drive_controller"]

        def feed(t: float) -> None:
            if round(t * 100) % 10 == 0:
                for w in range(nworld):
                    dd.set_cmd_vel(w, 0.3, 0.2)

        return feed
    fcc = manager["effort_controller"]

    def feed(t: float) -> None:
        if round(t * 500) % 50 == 0:
            for w in range(nworld):
                fcc.set_commands(w, np.zeros(len(fcc.joints)))

    return feed


def measure(model: str, nworld: int, seconds: float, only: str | None = None) -> tuple[float, float]:
    """(physics seconds per period, controller update seconds per period)."""
    sim, manager, substeps, period = setup(model, nworld, only)
    feed = (
        feeder(model, manager, nworld, np.random.default_rng(0))
        if not only or "Broadcaster" not in only
        else None
    )
    clock = {"t": 0.0}

    def physics() -> None:
        sim.write()
        sim.step(substeps)
        sim.read()

    def controllers() -> None:
        t = clock["t"]
        manager.update(sim, t, period)
        clock["t"] = t + period

    physics_t, control_t = [], []
    for _ in range(3):  # interleave so that both see the same machine state
        physics_t.append(median_time(physics, seconds / 6))
        t0 = time.perf_counter()
        n = 0
        samples = []
        while time.perf_counter() - t0 < seconds / 6 or n < 20:
            if feed is not None:  # message hand-over, timed apart: once per message, not per period
                feed(clock["t"])
            s = time.perf_counter()
            controllers()
            samples.append(time.perf_counter() - s)
            physics()  # the state moves on, as in the loop
            n += 1
        control_t.append(float(np.median(samples)))
    sim.shutdown()
    return min(physics_t), min(control_t)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", default="arm,car,quadruped")
    p.add_argument("--worlds", default="16,256,1024")
    p.add_argument("--seconds", type=float, default=2.0, help="per (model, worlds) pair")
    args = p.parse_args()

    print(
        f"# {platform.node()} | {os.cpu_count()} cores | {platform.processor() or platform.machine()} | "
        f"python {platform.python_version()} | mujoco {mujoco.__version__} | numpy {np.__version__} | "
        f"{time.strftime('%Y-%m-%d')}"
    )
    print(
        f"{'model':10s} {'controllers':44s} {'worlds':>6s} {'physics ms/period':>18s} "
        f"{'controllers us/period':>22s} {'ratio':>7s}"
    )
    bar = None
    for model in args.models.split(","):
        cases: list[tuple[str, str | None]] = [("default YAML", None)]
        if model == "arm":
            cases.append(
                ("JointTrajectoryController only", "joint_trajectory_controller/JointTrajectoryController")
            )
        for label, only in cases:
            names = ", ".join(
                load_controllers(default_controllers(model), batchsim.load(model), 1).controllers
            )
            what = names if only is None else label
            for nworld in (int(n) for n in args.worlds.split(",")):
                phys, ctrl = measure(model, nworld, args.seconds, only)
                ratio = ctrl / phys
                print(
                    f"{model:10s} {what[:44]:44s} {nworld:6d} {phys * 1e3:18.3f} {ctrl * 1e6:22.1f} {ratio:7.3f}",
                    flush=True,
                )
                if model == "arm" and only is not None and nworld == 1024:
                    bar = ratio
    if bar is not None:
        verdict = "ok" if bar < 1.0 else "FAILS"
        print(f"trajectory controller / physics at 1024 arms: {bar:.3f} ({verdict}: must be < 1)")


if __name__ == "__main__":
    main()
