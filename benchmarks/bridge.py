"""The ROS 2 bridge under load: the real-time factor a fleet holds while a second process
subscribes to every world's joint_states, and the messages per second it receives.

    .venv/bin/python benchmarks/bridge.py                       # the three standard runs
    .venv/bin/python benchmarks/bridge.py --worlds 16 --control-rate 1000 --publish-rate 1000

Each run starts `batchsim` (arm fleet, --controllers none: the raw bridge) as a
subprocess on a private ROS domain; this process is the subscriber. After discovery and
a warm-up, it counts joint_states messages over a window and reads the real-time factor
from batchsim's status lines over the same window. Not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time

STANDARD = [  # (worlds, control Hz, joint_states Hz)
    (16, 1000, 1000),
    (64, 100, 100),
    (256, 100, 100),
]


def run(
    worlds: int, control_rate: float, publish_rate: float, seconds: float, domain: int, threads: int, rtf: float = 1.0
) -> dict:
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState

    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "PYTHONUNBUFFERED": "1"}
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)
    cmd = [
        sys.executable, "-m", "batchsim.cli", "--worlds", str(worlds), "--model", "arm", "--controllers", "none",
        "--control-rate", str(control_rate), "--publish-rate", str(publish_rate), "--backend", "cpu", "--rtf", str(rtf),
    ]  # fmt: skip
    if threads:
        cmd += ["--threads", str(threads)]
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = Node("bridge_benchmark", context=context)
    counts = [0] * worlds

    def counter(w: int):
        def callback(msg: bytes) -> None:
            counts[w] += 1

        return callback

    # raw: count serialized messages, so a Python subscriber's deserialization does not
    # take the CPU the fleet needs on a 2-core machine
    for w in range(worlds):
        node.create_subscription(JointState, f"/world_{w}/joint_states", counter(w), 10, raw=True)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinning = threading.Thread(target=_spin, args=(executor,), daemon=True)
    spinning.start()
    try:
        start = time.monotonic()
        while not all(counts) and time.monotonic() - start < 120:
            if proc.poll() is not None:
                raise RuntimeError(f"batchsim exited:\n{open(log.name).read()}")
            time.sleep(0.2)
        discovery = time.monotonic() - start
        print(f"  {worlds} worlds: {sum(1 for c in counts if c)}/{worlds} publishing after {discovery:.1f} s", file=sys.stderr, flush=True)
        time.sleep(2.0)  # warm-up
        log.flush()
        lines_before = len(open(log.name).read().splitlines())
        c0, t0 = sum(counts), time.monotonic()
        time.sleep(seconds)
        c1, t1 = sum(counts), time.monotonic()
        status = open(log.name).read().splitlines()[lines_before:]
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        executor.shutdown()
        spinning.join(timeout=5)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    rtfs = [float(m.group(1)) for line in status if (m := re.search(r"rtf\s+([0-9.]+)", line))]
    expected = worlds * publish_rate * (statistics.median(rtfs) if rtfs else 0.0)
    return {
        "worlds": worlds,
        "control_hz": control_rate,
        "publish_hz": publish_rate,
        "rtf": statistics.median(rtfs) if rtfs else float("nan"),
        "rtf_min": min(rtfs) if rtfs else float("nan"),
        "received_per_s": (c1 - c0) / (t1 - t0),
        "published_per_s": expected,
        "discovery_s": discovery,
    }


def baseline(worlds: int, control_rate: float, threads: int, seconds: float) -> float:
    """The RTF the same fleet reaches with no ROS at all, as fast as it can (--no-ros --rtf 0)."""
    cmd = [
        sys.executable, "-m", "batchsim.cli", "--worlds", str(worlds), "--model", "arm", "--controllers", "none",
        "--control-rate", str(control_rate), "--backend", "cpu", "--rtf", "0", "--no-ros",
    ]  # fmt: skip
    if threads:
        cmd += ["--threads", str(threads)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    time.sleep(seconds)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=20)
    rtfs = [float(m.group(1)) for line in out.splitlines() if (m := re.search(r"\| rtf\s+([0-9.]+)", line))]
    return statistics.median(rtfs[1:] or rtfs) if rtfs else float("nan")


def _spin(executor) -> None:
    try:
        executor.spin()
    except Exception:  # shut down under it
        pass


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=None)
    p.add_argument("--control-rate", type=float, default=1000.0)
    p.add_argument("--publish-rate", type=float, default=None)
    p.add_argument("--seconds", type=float, default=10.0, help="measurement window (wall)")
    p.add_argument("--domain", type=int, default=70)
    p.add_argument("--rtf", type=float, default=1.0, help="the RTF batchsim is asked to hold; 0: as fast as it can")
    p.add_argument(
        "--threads", type=int, default=1,
        help="physics threads of the cpu backend (default 1: the subscriber needs the other core; 0: batchsim's default)",
    )  # fmt: skip
    args = p.parse_args()
    runs = (
        [(args.worlds, args.control_rate, args.publish_rate or args.control_rate)] if args.worlds else STANDARD
    )
    print(
        f"# {os.cpu_count()} cores, Python {platform.python_version()}, physics threads {args.threads or 'default'}, rtf asked {args.rtf:g}, "
        f"load average {os.getloadavg()[0]:.1f}, {time.strftime('%Y-%m-%d')}"
    )
    print(
        "| worlds | control Hz | joint_states Hz per world | RTF without ROS, flat out | RTF held with the bridge "
        "(median / min) | joint_states received/s | expected/s | discovery s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for worlds, control, publish in runs:
        flat_out = baseline(worlds, control, args.threads, min(args.seconds, 6.0))
        r = run(worlds, control, publish, args.seconds, args.domain, args.threads, args.rtf)
        print(
            f"| {r['worlds']} | {r['control_hz']:g} | {r['publish_hz']:g} | {flat_out:.2f} | "
            f"{r['rtf']:.2f} / {r['rtf_min']:.2f} | "
            f"{r['received_per_s']:,.0f} | {r['published_per_s']:,.0f} | {r['discovery_s']:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
