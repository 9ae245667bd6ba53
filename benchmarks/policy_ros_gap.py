"""The same policy with and without the ROS path: each world's target written in-process
(`batchsim evaluate`'s path) against the same target sent over DDS to a running fleet.

Both run examples/policies/arm_reach.onnx on N arms with randomize.yaml's draws (world i's
draw 0 in both) and give world i the same target (batchsim.evaluation.commands, seed 0):

  in-process  batchsim.evaluation.run_episodes: one episode, the command set before its first
              period, the loop at full speed
  ros         `batchsim --worlds N --controllers arm_reach.yaml --randomize randomize.yaml` in a
              subprocess, paced at real time; this process (an rclpy node on its own
              ROS_DOMAIN_ID, LOCALHOST discovery) publishes every world's target on
              /world_<i>/arm_reach_controller/command at once and records /world_<i>/joint_states

Measured per world, from the sim time the command was given (in-process: 0; ros: the newest
joint_states stamp when it was published): the motion's start (the first sample at which any
joint moved 1 mrad), the error at `--seconds` (success: below 0.1 rad), the tracking error
(mean over the last quarter) and the time to target. The gap is the difference of the two rows.

    python benchmarks/policy_ros_gap.py [--worlds 16] [--seconds 3] [--domain 57]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import mujoco
import numpy as np

import batchsim
from batchsim.controllers import load_controllers
from batchsim.evaluation.commands import draw_commands
from batchsim.evaluation.episodes import EvalOptions, find_policy, run_episodes
from batchsim.loop import SimLoop

HERE = Path(__file__).resolve().parent.parent / "examples" / "policies"
YAML, RANDOMIZE = HERE / "arm_reach.yaml", HERE / "randomize.yaml"
JOINTS = [f"joint{i}" for i in range(1, 7)]
TOLERANCE = 0.1


def metrics(t: np.ndarray, q: np.ndarray, target: np.ndarray, seconds: float) -> dict[str, float]:
    """One world's samples `t` (k,) s after the command and positions `q` (k, 6)."""
    error = np.abs(q - target).max(axis=1)
    moved = np.abs(q - q[0]).max(axis=1) > 1e-3
    within = t <= seconds + 1e-9
    t, error, moved = t[within], error[within], moved[within]
    below = np.flatnonzero(error < TOLERANCE)
    return {
        "start": float(t[np.argmax(moved)]) if moved.any() else np.nan,
        "final": float(error[-1]),
        "tracking": float(error[t >= 0.75 * seconds].mean()),
        "reach": float(t[below[0]]) if below.size else np.nan,
    }


def in_process(n: int, seconds: float) -> list[dict[str, float]]:
    sim = batchsim.make("arm", n, "cpu", randomize=str(RANDOMIZE))
    sim.configure()
    sim.activate()
    manager = load_controllers(YAML, sim.spec, n)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    policy = find_policy(manager, None)
    names = sim.export_state_interfaces()
    pos = [names.index(f"{j}/position") for j in JOINTS]
    samples: list[np.ndarray] = []

    class Recorder:  # each period's read, as joint_states would carry it
        def update(self, sim, time, period):
            samples.append(sim.state[:, pos].copy())

    loop.participants.append(Recorder())
    run_episodes(sim, manager, loop, policy, EvalOptions(episodes=1, seconds=seconds), 0)
    q = np.stack(samples, axis=1)  # (n, k, 6)
    t = np.arange(q.shape[1]) * loop.period
    targets = draw_commands(policy.policy.command_ranges, 0, np.arange(n), np.zeros(n))
    return [metrics(t, q[w], targets[w], seconds) for w in range(n)]


def over_ros(n: int, seconds: float, domain: int) -> tuple[list[dict[str, float]], float]:
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    exe = shutil.which("batchsim") or str(Path(sys.executable).parent / "batchsim")
    args = [
        exe,
        "--model",
        "arm",
        "--backend",
        "cpu",
        "--worlds",
        str(n),
        "--controllers",
        str(YAML),
        "--randomize",
        str(RANDOMIZE),
    ]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    rclpy.init()
    node = rclpy.create_node("policy_ros_gap")
    lock = threading.Lock()
    samples: list[list[tuple[float, np.ndarray]]] = [[] for _ in range(n)]

    def on_state(w: int):
        def callback(msg: JointState) -> None:
            order = [list(msg.name).index(j) for j in JOINTS]
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            with lock:
                samples[w].append((stamp, np.asarray(msg.position)[order]))

        return callback

    subs = [
        node.create_subscription(JointState, f"/world_{w}/joint_states", on_state(w), 50) for w in range(n)
    ]
    pubs = [
        node.create_publisher(Float64MultiArray, f"/world_{w}/arm_reach_controller/command", 10)
        for w in range(n)
    ]
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        deadline = time.monotonic() + 120
        while not (all(samples) and all(p.get_subscription_count() for p in pubs)):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(
                    f"the fleet did not come up: {proc.stderr.read() if proc.poll() is not None else 'timeout'}"
                )
            time.sleep(0.1)
        time.sleep(1.0)  # settled at the start pose
        targets = draw_commands(_ranges(), 0, np.arange(n), np.zeros(n))
        with lock:
            t0 = max(s[-1][0] for s in samples)
        wall0 = time.monotonic()
        for w in range(n):
            pubs[w].publish(Float64MultiArray(data=targets[w].tolist()))
        while True:
            with lock:
                newest = min(s[-1][0] for s in samples)
            if newest >= t0 + seconds + 0.2:
                break
            time.sleep(0.05)
        rtf = (newest - t0) / (time.monotonic() - wall0)
        out = []
        for w in range(n):
            with lock:
                rows = [(t - t0, q) for t, q in samples[w] if t >= t0 - 1e-9]
            t = np.array([r[0] for r in rows])
            q = np.stack([r[1] for r in rows])
            out.append(metrics(t, q, targets[w], seconds))
        return out, rtf
    finally:
        executor.shutdown()
        del subs
        node.destroy_node()
        rclpy.shutdown()
        proc.terminate()
        proc.wait(timeout=30)


def _ranges() -> np.ndarray:
    from batchsim.evaluation.policy_file import read_policy_yaml

    return read_policy_yaml(YAML)[1].command_ranges


def row(name: str, results: list[dict[str, float]]) -> str:
    def s(key: str, scale: float = 1.0) -> str:
        v = np.array([r[key] for r in results]) * scale
        v = v[np.isfinite(v)]
        return f"{np.median(v):7.3f} {v.max():7.3f}" if v.size else f"{'-':>7} {'-':>7}"

    success = np.mean([r["final"] < TOLERANCE for r in results])
    return f"{name:>10} | {100 * success:6.1f}% | {s('start', 1e3)} | {s('tracking')} | {s('reach')}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--domain", type=int, default=57)
    args = parser.parse_args()
    print(f"# {platform.node()} {platform.machine()}, {os.cpu_count()} cores, mujoco {mujoco.__version__}, numpy {np.__version__}, "
          f"Python {platform.python_version()}, {time.strftime('%Y-%m-%d')}; {args.worlds} arms, {args.seconds:g} s")  # fmt: skip
    local = in_process(args.worlds, args.seconds)
    ros, rtf = over_ros(args.worlds, args.seconds, args.domain)
    print(f"{'path':>10} | success | motion start (ms) | tracking error (rad) | time to target (s)")
    print(f"{'':>10} |         |  median   worst  |  median   worst     |  median   worst")
    print(row("in-process", local))
    print(row("ros", ros))
    gap = np.array([r["final"] for r in ros]) - np.array([r["final"] for r in local])
    print(f"final error, ros minus in-process, per world: median {np.median(gap):+.4f}, largest {gap[np.argmax(np.abs(gap))]:+.4f} rad; "
          f"ros run's real-time factor over the episode {rtf:.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
