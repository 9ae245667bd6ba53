"""What the PID path costs per control period: write() with position interfaces through
PIDs on torque motors, against write() copying effort commands straight into ctrl, beside
the physics of the same period, all in one run on the cpu backend.

    .venv/bin/python benchmarks/actuation.py [--worlds 16,256,1024] [--periods 500]

Model: the shipped quadruped (12 torque motors, 1 kHz physics, 100 Hz control), once as
the MJCF gives it (12 effort interfaces: a plain copy) and once with a ros2_control block
asking for position on every joint, with gains from a pids_config_file. Prints the median
and worst write() and step() time per period, in microseconds.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import batchsim


def description(spec: batchsim.RobotSpec, folder: Path) -> Path:
    joints = [j.name for j in spec.joints]
    (folder / "pids.yaml").write_text(
        "/**:\n  ros__parameters:\n    pid_gains:\n      position:\n"
        + "".join(f"        {j}: {{p: 40.0, i: 1.0, d: 2.0, u_clamp_max: 30.0, u_clamp_min: -30.0}}\n" for j in joints)
    )
    body = "".join(f'<joint name="{j}"><command_interface name="position"/><state_interface name="position"/></joint>' for j in joints)
    path = folder / "quadruped.ros2_control.xml"
    path.write_text(
        '<robot name="q"><ros2_control name="q" type="system"><hardware><plugin>x</plugin>'
        f'<param name="pids_config_file">pids.yaml</param></hardware>{body}</ros2_control></robot>'
    )
    return path


def measure(sim: batchsim.BatchedSystem, periods: int, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    write, step = np.zeros(periods), np.zeros(periods)
    for k in range(periods):
        sim.read()
        t0 = time.perf_counter()
        sim.write()
        t1 = time.perf_counter()
        sim.step(substeps)
        t2 = time.perf_counter()
        write[k], step[k] = t1 - t0, t2 - t1
    return write * 1e6, step * 1e6


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", default="16,256,1024")
    p.add_argument("--periods", type=int, default=500)
    args = p.parse_args()
    base = batchsim.load("quadruped")
    substeps = round(0.01 / base.mjmodel.opt.timestep)
    print(f"{'worlds':>6}  {'path':<22}{'write median':>13}{'write worst':>12}{'step median':>12}{'step worst':>11}  (us/period)")
    with tempfile.TemporaryDirectory() as tmp:
        pid_block = description(base, Path(tmp))
        for nworld in (int(n) for n in args.worlds.split(",")):
            for label, kwargs in (("effort copy", {}), ("position through PIDs", {"ros2_control": pid_block})):
                sim = batchsim.make("quadruped", nworld, "cpu", **kwargs)
                sim.configure()
                sim.activate()
                measure(sim, 20, substeps)  # warm up
                write, step = measure(sim, args.periods, substeps)
                print(
                    f"{nworld:>6}  {label:<22}{np.median(write):>13.1f}{write.max():>12.1f}"
                    f"{np.median(step):>12.1f}{step.max():>11.1f}"
                )
                sim.shutdown()


if __name__ == "__main__":
    main()
