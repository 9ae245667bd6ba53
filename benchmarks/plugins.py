"""What mujoco_ros2_control's plugins cost a control period, side by side in one run.

Upstream's demo 05 mobile base (tests/upstream: scene_mobile_base.xml, mobile_base.urdf, its
controllers) runs a period (`read(); write(); step(substeps)`) three ways, interleaved:

  plain:    no plugin configured
  velocity: the BaseVelocityPlugin, every world commanded (its free base held before every substep)
  wrench:   the ExternalWrenchPlugin, a wrench running on every world's base (rotated and
            transported on the host at each write())

Prints the median and the worst period per variant and fleet size (a period's deadline is
the control period: 10 ms at 100 Hz).

    python benchmarks/plugins.py [--worlds 16,256] [--periods 300] [--backend cpu]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import mujoco
import numpy as np

import batchsim
from batchsim.plugins.external_wrench import ExternalWrench

DEMOS = Path(__file__).resolve().parent.parent / "tests" / "upstream" / "mujoco_ros2_control_demos"
SCENE = DEMOS / "demo_resources" / "scenes" / "scene_mobile_base.xml"
URDF = DEMOS / "demo_resources" / "mobile_base" / "mobile_base.urdf"
PLUGINS = {
    "velocity": {"base_velocity_plugin": {"type": "mujoco_ros2_control_plugins/BaseVelocityPlugin", "body": "base_link"}},
    "wrench": {"external_wrench": {"type": "mujoco_ros2_control_plugins/ExternalWrenchPlugin"}},
}
SUBSTEPS = 5  # the demo's 100 Hz control period of 2 ms steps


def make(variant: str, nworld: int, backend: str) -> batchsim.BatchedSystem:
    sensors = None
    if variant in PLUGINS:
        sensors = {"/**": {"ros__parameters": {"mujoco_plugins": PLUGINS[variant]}}}
    sim = batchsim.make(str(SCENE), nworld, backend, ros2_control=str(URDF), sensors=sensors)
    sim.configure()
    sim.activate()
    sim.read()
    if variant == "velocity":
        sim.set_base_velocity(np.tile([0.3, 0.1, 0.2], (nworld, 1)))
    elif variant == "wrench":
        sim.apply_wrench(ExternalWrench("base_link", force=(5.0, 0.0, 0.0), duration=1e6))
    return sim


def period(sim: batchsim.BatchedSystem) -> float:
    t0 = time.perf_counter()
    sim.read()
    sim.write()
    sim.step(SUBSTEPS)
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", default="16,256")
    p.add_argument("--periods", type=int, default=300)
    p.add_argument("--backend", default="cpu")
    args = p.parse_args()
    print(
        f"# {platform.node() or 'host'}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"mujoco {mujoco.__version__}, numpy {np.__version__}, backend {args.backend}, "
        f"{time.strftime('%Y-%m-%d')}"
    )
    print("| worlds | variant | median ms | worst ms | median vs plain |")
    print("| --- | --- | --- | --- | --- |")
    for nworld in (int(n) for n in args.worlds.split(",")):
        sims = {v: make(v, nworld, args.backend) for v in ("plain", "velocity", "wrench")}
        for sim in sims.values():  # warm-up
            for _ in range(20):
                period(sim)
        times: dict[str, list[float]] = {v: [] for v in sims}
        for _ in range(args.periods):  # interleaved: the machine's drift falls on every variant alike
            for v, sim in sims.items():
                times[v].append(period(sim))
        plain = float(np.median(times["plain"]))
        for v, t in times.items():
            med, worst = float(np.median(t)), float(np.max(t))
            print(f"| {nworld} | {v} | {med * 1e3:.2f} | {worst * 1e3:.2f} | {med / plain:.2f}x |")
        for sim in sims.values():
            sim.shutdown()


if __name__ == "__main__":
    main()
