"""A flood on one world against its neighbours' joint_states (issue 23, defect 4).

    .venv/bin/python benchmarks/flood.py                       # 16 arms, 1 bridge worker, flood world 3
    .venv/bin/python benchmarks/flood.py --topic commands --seconds 5

A `batchsim` fleet (`--bridge-workers 1`: every world on the same worker) on a private ROS
domain; one process counts every world's joint_states (raw, so it costs little) and notes
each one's sim stamp; one more process publishes to world 3 as fast as it can (a valid
trajectory on `joint_trajectory_controller/joint_trajectory`, or a `commands` vector the
controller's claim rejects). Two windows of the same length, quiet then flooded; per world
and window: joint_states received per wall second, the share of sim periods whose state
arrived (1.00: none skipped), and the longest wall gap between two. The flooded world's
own rate and the worker's /diagnostics counts for it are printed too. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))  # fleet.py beside it, also when imported as benchmarks.flood
from fleet import executor_until_stdin_closes  # noqa: E402

LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
JOINTS = [f"joint{j}" for j in range(1, 7)]
TOPICS = {"trajectory": "joint_trajectory_controller/joint_trajectory", "commands": "commands"}


def _init(domain: int, name: str):
    os.environ.update(LOCALHOST)
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    return context, Node(name, context=context)


def counter(domain: int, nworld: int, out: str) -> None:
    """Every world's joint_states, raw: (world, wall time, sim stamp) of each, saved to `out`
    when stdin closes."""
    from sensor_msgs.msg import JointState

    context, node = _init(domain, "flood_counter")
    rows: list[tuple[int, float, float]] = []

    def sink(w: int):
        def callback(raw: bytes) -> None:  # CDR: 4 bytes of header, then the stamp's sec, nanosec
            sec, nanosec = int.from_bytes(raw[4:8], "little", signed=True), int.from_bytes(raw[8:12], "little")
            rows.append((w, time.monotonic(), sec + nanosec * 1e-9))

        return callback

    for w in range(nworld):
        node.create_subscription(JointState, f"/world_{w}/joint_states", sink(w), 10, raw=True)
    executor, stop = executor_until_stdin_closes(context, node)
    print("ready", flush=True)
    heard, deadline = False, time.monotonic() + 60
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        if not heard and len({int(r[0]) for r in rows[-20 * nworld :]}) == nworld:
            heard = True
            print("heard", flush=True)  # every world
        elif not heard and time.monotonic() > deadline:
            heard = True
            print("not every world heard in 60 s", flush=True)
    np.save(out, np.array(rows, dtype=np.float64).reshape(-1, 3))


def flooder(domain: int, world: int, kind: str, seconds: float, points: int = 1) -> None:
    """Publish to `world` as fast as one Python process can for `seconds`; print how many."""
    from builtin_interfaces.msg import Duration
    from std_msgs.msg import Float64MultiArray
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    _context, node = _init(domain, "flooder")
    topic = f"/world_{world}/{TOPICS[kind]}"
    if kind == "trajectory":
        step = 200_000_000 // points
        pts = [JointTrajectoryPoint(positions=[0.1] * 6, time_from_start=Duration(nanosec=step * (i + 1))) for i in range(points)]
        msg, msg_type = JointTrajectory(joint_names=JOINTS, points=pts), JointTrajectory
    else:
        msg, msg_type = Float64MultiArray(data=[0.1] * 6), Float64MultiArray
    pub = node.create_publisher(msg_type, topic, 10)
    deadline = time.monotonic() + 20
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    print("matched", flush=True)
    sys.stdin.readline()  # go
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        for _ in range(100):
            pub.publish(msg)
        n += 100
    print(f"sent {n}", flush=True)


def diagnostics(domain: int, world: int) -> None:
    """Print world `world`'s /diagnostics values once a second until stdin closes."""
    from diagnostic_msgs.msg import DiagnosticArray

    context, node = _init(domain, "flood_diagnostics")
    last: dict[str, str] = {}

    def callback(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.hardware_id == f"world_{world}":
                last.update({kv.key: kv.value for kv in status.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", callback, 100)
    executor, stop = executor_until_stdin_closes(context, node)
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
    print(" | ".join(f"{k}: {v}" for k, v in last.items()), flush=True)


def _child(*args: str) -> subprocess.Popen:
    env = {**os.environ, **LOCALHOST, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, __file__, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)


def window(rows: np.ndarray, w: int, t0: float, t1: float, rate: float) -> tuple[float, float, float]:
    """joint_states/s of world w in wall window [t0, t1), the share of its sim periods heard, the longest gap."""
    mine = rows[(rows[:, 0] == w) & (rows[:, 1] >= t0) & (rows[:, 1] < t1)]
    if len(mine) < 2:
        return 0.0, 0.0, t1 - t0
    periods = (mine[-1, 2] - mine[0, 2]) * rate + 1
    return len(mine) / (t1 - t0), len(np.unique(mine[:, 2])) / periods, float(np.diff(mine[:, 1]).max())


def run(domain: int, worlds: int = 16, world: int = 3, topic: str = "trajectory", seconds: float = 5.0,
        rate: float = 100.0, log: str = "/tmp/flood_batchsim.log", settle: float = 3.0, points: int = 1) -> dict:
    """One fleet, a quiet window and a flooded one of `seconds` each. Returns per world
    (world -> (quiet, flood), each (joint_states/s, share of sim periods heard, longest gap s)),
    the messages sent, the flood's wall seconds, and the flooded world's last /diagnostics values."""
    out = f"/tmp/flood_{os.getpid()}_{domain}.npy"
    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain), "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "batchsim.cli", "--quiet", "--worlds", str(worlds), "--bridge-workers", "1"]
    cmd += ["--model", "arm", "--publish-rate", str(rate), "--control-rate", str(rate), "--backend", "cpu"]
    with open(log, "w") as log_file:
        fleet = subprocess.Popen(cmd, env=env, stdout=log_file, stderr=subprocess.STDOUT)
        count = _child("--child", "counter", str(domain), str(worlds), out)
        diag = _child("--child", "diagnostics", str(domain), str(world))
        flood = _child("--child", "flooder", str(domain), str(world), topic, str(seconds), str(points))
        try:
            started = [count.stdout.readline().strip(), flood.stdout.readline().strip(), count.stdout.readline().strip()]
            if started != ["ready", "matched", "heard"]:
                raise RuntimeError(f"the counter or the flooder did not start ({started}); see {log}")
            time.sleep(settle)  # discovery settled
            t0 = time.monotonic()
            time.sleep(seconds)
            t1 = time.monotonic()
            flood.stdin.write("go\n")
            flood.stdin.flush()
            sent = int(flood.stdout.readline().split()[-1])
            t2 = time.monotonic()
            time.sleep(1.0)  # /diagnostics: twice a second
        finally:
            for p in (count, diag, flood):
                p.stdin.close()
            count.wait(10)
            values = dict(line.split(": ", 1) for line in diag.stdout.read().strip().split(" | ") if ": " in line)
            flood.wait(10)
            fleet.send_signal(signal.SIGINT)
            fleet.wait(10)
    rows = np.load(out)
    os.unlink(out)
    per_world = {w: (window(rows, w, t0, t1, rate), window(rows, w, t1, t2, rate)) for w in range(worlds)}
    return {"worlds": per_world, "sent": sent, "seconds": t2 - t1, "diagnostics": values}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", type=int, default=16)
    ap.add_argument("--world", type=int, default=3, help="the flooded world")
    ap.add_argument("--topic", choices=sorted(TOPICS), default="trajectory")
    ap.add_argument("--seconds", type=float, default=5.0, help="each window")
    ap.add_argument("--rate", type=float, default=100.0, help="publish rate asked, Hz")
    ap.add_argument("--points", type=int, default=1, help="points per flooding trajectory")
    ap.add_argument("--domain", type=int, default=57)
    ap.add_argument("--log", default="/tmp/flood_batchsim.log", help="batchsim's output")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        kind, *rest = a.child
        {"counter": lambda: counter(int(rest[0]), int(rest[1]), rest[2]),
         "flooder": lambda: flooder(int(rest[0]), int(rest[1]), rest[2], float(rest[3]), int(rest[4])),
         "diagnostics": lambda: diagnostics(int(rest[0]), int(rest[1]))}[kind]()  # fmt: skip
        return
    r = run(a.domain, a.worlds, a.world, a.topic, a.seconds, a.rate, a.log, points=a.points)
    print(f"# {platform.node()} | {os.cpu_count()} cores | load {os.getloadavg()[0]:.2f} | {a.worlds} worlds, 1 bridge worker, "
          f"publish {a.rate:g} Hz | flood: {r['sent']} messages in {r['seconds']:.1f} s on /world_{a.world}/{TOPICS[a.topic]}")  # fmt: skip
    print(f"{'world':>5} | {'quiet /s':>8} {'heard':>5} {'gap s':>5} | {'flood /s':>8} {'heard':>5} {'gap s':>5}")
    for w, (q, f) in r["worlds"].items():
        mark = "   <- flooded" if w == a.world else ""
        print(f"{w:>5} | {q[0]:8.1f} {q[1]:5.2f} {q[2]:5.2f} | {f[0]:8.1f} {f[1]:5.2f} {f[2]:5.2f}{mark}")
    qs = np.array([q for w, (q, _f) in r["worlds"].items() if w != a.world])
    fs = np.array([f for w, (_q, f) in r["worlds"].items() if w != a.world])
    print(f"others: quiet {qs[:, 0].min():.1f}-{qs[:, 0].max():.1f}/s (worst gap {qs[:, 2].max():.2f} s); "
          f"flood {fs[:, 0].min():.1f}-{fs[:, 0].max():.1f}/s (worst gap {fs[:, 2].max():.2f} s), "
          f"sim periods heard >= {fs[:, 1].min():.2f}")  # fmt: skip
    wanted = ("rejected", "published")
    print(f"world_{a.world} /diagnostics: " + " | ".join(f"{k}: {v}" for k, v in r["diagnostics"].items() if k.startswith(wanted)))


if __name__ == "__main__":
    main()
