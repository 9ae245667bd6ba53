"""Calibration against a "real" robot made honestly: the shipped arm run by batchsim with hidden
parameter changes (link2 and link3 masses, joint2's damping, joint1's servo gain:
batchsim.calibration.synthetic.HIDDEN_ARM), driven by seeded trajectories through its
joint_trajectory_controller and written as a rosbag2 MCAP with 2e-4 rad of measurement noise.
The calibration is told only the bag, the model and the ranges (RANGES_ARM); this prints how its
error and its parameter error fall with the worlds per round and the rounds.

    .venv/bin/python benchmarks/calibration.py [--grid 32x5,128x2,128x5,512x5] [--seconds 6]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import batchsim
from batchsim.calibration import synthetic
from batchsim.calibration.bag import read_bag
from batchsim.calibration.fit import FitOptions, calibrate
from batchsim.calibration.replay import controller_inputs
from batchsim.controllers import default_controllers, load_controllers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", default="32x5,128x2,128x5,512x5", help="worlds x rounds, comma separated")
    parser.add_argument("--seconds", type=float, default=6.0, help="the bag's length")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--backend", default="cpu", help="where the worlds of each round run (cpu, warp, mjx)")
    args = parser.parse_args()
    import platform

    import mujoco

    print(f"# {platform.node()}: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; MuJoCo {mujoco.__version__}; "
          f"backend {args.backend}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        path = synthetic.write_bag(Path(tmp) / "real.mcap", "arm", synthetic.HIDDEN_ARM, seconds=args.seconds, seed=1)
        spec = batchsim.load("arm")
        controllers = default_controllers("arm")
        inputs = controller_inputs(load_controllers(controllers, spec, 1))
        bag = read_bag(path, [j.name for j in spec.joints], {t: i.kind for t, i in inputs.items()})
        hidden = [synthetic.HIDDEN_ARM_FITTED[f][o] for f, objects in synthetic.HIDDEN_ARM_FITTED.items() for o in objects]
        labels = [f"{f} {o}" for f, objects in synthetic.HIDDEN_ARM_FITTED.items() for o in objects]
        print(f"bag: {len(bag.times)} joint states over {bag.duration:g} s, {len(bag.commands)} trajectories; hidden: "
              + ", ".join(f"{label} x{v:g}" for label, v in zip(labels, hidden, strict=True)))
        print(f"load before: {os.getloadavg()[0]:.2f} (1-min), {os.cpu_count()} cores")
        header = f"| worlds | rounds | error before | error after | {' | '.join(labels)} | worst param error | wall s | load |"
        print(header)
        print("|" + "---|" * (header.count("|") - 1))
        for cell in args.grid.split(","):
            worlds, rounds = (int(v) for v in cell.split("x"))
            start = time.perf_counter()
            fit = calibrate(bag, "arm", synthetic.RANGES_ARM, controllers, FitOptions(worlds, rounds, seed=args.seed, backend=args.backend))
            wall = time.perf_counter() - start
            got = {p.label: v for p, v in zip(fit.params, fit.fitted.tolist(), strict=True)}
            fitted = [got[label] for label in labels]
            worst = max(abs(f - h) / h for f, h in zip(fitted, hidden, strict=True))
            print(
                f"| {worlds} | {rounds} | {float(fit.before.overall[0]):.2e} | {float(fit.after.overall[0]):.2e} | "
                + " | ".join(f"{v:.3f}" for v in fitted)
                + f" | {100 * worst:.1f} % | {wall:.1f} | {os.getloadavg()[0]:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
