"""What the policy controller costs per control period, against the same fleet with a
joint_trajectory_controller, and what ONNX Runtime's batched call costs by itself.

Both fleets are the arm on one backend (`--backend`, default cpu) with its randomization (examples/policies/), run
as the loop runs them (read, manager.update, write, step), interleaved period by period so
that both see the same machine:

  policy  examples/policies/arm_reach.yaml: arm_reach.onnx at 50 Hz in a 100 Hz loop (an
          inference every second period, the target held between); every world gets a new
          target every 1 s, all in the same period (`set_commands`, as the bridge hands them)
  jtc     the arm's default controllers: every world gets a new 10-point trajectory every
          1 s, all in the same period (`set_trajectories`, as the bridge hands them)

Reported per fleet size: read() (on a device backend, the state coming to the host: what the
policy's observation is built from), the controllers' share of a period (hand-over + update),
each median, 99th percentile and worst, and the whole period likewise; then ONNX Runtime's call
alone on (nworld, nobs) float32, median and worst. What a period's deadline holds is the whole
period. On a device backend (warp, mjx) the first periods compile and are not recorded.

    python benchmarks/policy.py [--worlds 16,256,1024] [--seconds 3] [--backend cpu]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import mujoco
import numpy as np
import onnxruntime

import batchsim
from batchsim.controllers import TrajectoryBatch, default_controllers, load_controllers
from batchsim.controllers.policy import PolicyController

HERE = Path(__file__).resolve().parent.parent / "examples" / "policies"
RATE = 100.0


class Fleet:
    """One fleet, its manager and its per-period hand-over."""

    def __init__(self, kind: str, nworld: int, backend: str = "cpu"):
        self.kind = kind
        self.sim = sim = batchsim.make("arm", nworld, backend, randomize=str(HERE / "randomize.yaml"))
        sim.configure()
        sim.activate()
        source = HERE / "arm_reach.yaml" if kind == "policy" else default_controllers("arm")
        self.manager = load_controllers(source, sim.spec, nworld)
        self.nstep = round(1.0 / (RATE * sim.dt))
        self.t = 0.0
        self.rng = np.random.default_rng(0)
        self.controller = next(
            c
            for c in self.manager
            if isinstance(c, PolicyController) or c.name == "joint_trajectory_controller"
        )
        self.read, self.control, self.total = [], [], []

    def hand_over(self, k: int) -> None:
        if k % int(RATE) != 0:  # once a second, every world at once
            return
        n = self.sim.nworld
        targets = self.rng.uniform(-0.8, 0.8, (n, 6))
        if self.kind == "policy":
            self.controller.set_commands(np.arange(n), targets)
            return
        npoint = 10
        times = np.tile(np.linspace(0.1, 1.0, npoint), n)
        positions = np.repeat(targets, npoint, axis=0) * np.tile(np.linspace(0.1, 1.0, npoint), n)[:, None]
        batch = TrajectoryBatch(
            worlds=np.arange(n), start_time=np.zeros(n), joint_mask=np.ones((n, 6), bool),
            offsets=np.arange(n + 1) * npoint, times=times, positions=positions,
        )  # fmt: skip
        self.controller.set_trajectories(batch)

    def period(self, k: int, record: bool) -> None:
        sim, period = self.sim, 1.0 / RATE
        t0 = time.perf_counter()
        sim.read(self.t, period)
        t1 = time.perf_counter()
        self.hand_over(k)
        self.manager.update(sim, self.t, period)
        t2 = time.perf_counter()
        sim.write(self.t, period)
        sim.step(self.nstep)
        t3 = time.perf_counter()
        self.t += period
        if record:
            self.read.append(t1 - t0)
            self.control.append(t2 - t1)
            self.total.append(t3 - t0)


def stats(samples: list[float]) -> str:
    s = np.asarray(samples) * 1e6
    return f"{np.median(s):9.0f} {np.percentile(s, 99):9.0f} {s.max():9.0f}"


def onnx_alone(nworld: int, seconds: float) -> str:  # the cpu backend's fleet: ONNX Runtime is the same
    policy = Fleet("policy", nworld).controller
    obs = np.random.default_rng(0).normal(size=(nworld, policy.policy.obs_size)).astype(np.float32)
    for _ in range(20):
        policy.runtime(obs)
    samples = []
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline or len(samples) < 100:
        t0 = time.perf_counter()
        policy.runtime(obs)
        samples.append(time.perf_counter() - t0)
    return stats(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", default="16,256,1024")
    parser.add_argument(
        "--seconds",
        type=float,
        default=3.0,
        help="sim seconds recorded per fleet size, after 0.5 s of warm-up",
    )
    parser.add_argument("--backend", default="cpu", help="cpu, warp or mjx (a device backend: the state read to the host)")
    parser.add_argument("--warmup", type=float, default=0.5, help="sim seconds run first, not recorded (a GPU compiles in them)")
    args = parser.parse_args()
    print(f"# {platform.node()} {platform.processor() or platform.machine()}, mujoco {mujoco.__version__}, "
          f"onnxruntime {onnxruntime.__version__} ({','.join(onnxruntime.get_available_providers())}), numpy {np.__version__}, "
          f"Python {platform.python_version()}, {time.strftime('%Y-%m-%d')}; backend {args.backend}")  # fmt: skip
    print("# microseconds per control period: median, p99, worst")
    print(f"{'worlds':>6} {'fleet':>7} | {'read':^29} | {'controllers':^29} | {'whole period':^29}")
    for nworld in (int(w) for w in args.worlds.split(",")):
        fleets = [Fleet("policy", nworld, args.backend), Fleet("jtc", nworld, args.backend)]
        warm, total = int(args.warmup * RATE), int((args.warmup + args.seconds) * RATE)
        for k in range(total):
            for fleet in fleets:  # interleaved: both see the same machine
                fleet.period(k, record=k >= warm)
        for fleet in fleets:
            print(f"{nworld:>6} {fleet.kind:>7} | {stats(fleet.read)} | {stats(fleet.control)} | {stats(fleet.total)}")
            fleet.sim.shutdown()
        print(f"{nworld:>6} {'onnx':>7} | {'':29} | {onnx_alone(nworld, 1.0)} |  (ONNX Runtime's call alone)")


if __name__ == "__main__":
    main()
