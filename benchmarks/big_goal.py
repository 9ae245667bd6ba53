"""What one very large FollowJointTrajectory goal costs a bridge worker's memory, and whether it
is given back (issue 47's review: a 1,000,000-point goal added 700-800 MB to the worker, which
kept it).

    .venv/bin/python benchmarks/big_goal.py --points 1000000 --after 90

`batchsim --worlds 2` (the arm, its controllers, one bridge worker process); a client sends world
0's joint_trajectory_controller one goal of `--points` points (above max_trajectory_points: it
is aborted with the reason), waits for its result, and the worker's resident memory (VmRSS) is
read before the goal, at its highest while the goal is handled, and each 10 s after until
`--after` seconds. rclpy keeps a finished goal (its request included) for the action server's
result_timeout, and glibc keeps the pages of a heap that grew unless trimmed.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import LOCALHOST, _pythonpath, _versions  # noqa: E402


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def worker_pid(parent: int) -> int | None:
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read()
        except OSError:
            continue
        if ppid == parent and b"ros_bridge.worker" in cmd and b"recorder" not in cmd and b"view" not in cmd:
            return int(pid)
    return None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=1_000_000)
    p.add_argument("--after", type=float, default=90.0)
    p.add_argument("--goals", type=int, default=1, help="goals sent one after the other")
    p.add_argument("--domain", type=int, default=77)
    opts = p.parse_args()
    import rclpy
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from trajectory_msgs.msg import JointTrajectoryPoint

    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(opts.domain), "PYTHONPATH": _pythonpath()}
    cmd = [sys.executable, "-m", "batchsim.cli", "--worlds", "2", "--bridge-workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env)
    context = Context()
    try:
        for line in proc.stderr:
            if line.startswith("batchsim: ") and " x " in line:
                break
        log = open(os.environ.get("BIG_GOAL_LOG", os.devnull), "w")
        threading.Thread(target=lambda: [log.write(line) for line in proc.stderr], daemon=True).start()
        worker = worker_pid(proc.pid)
        assert worker is not None, "no bridge worker process"
        os.environ.update(LOCALHOST)
        rclpy.init(context=context, domain_id=opts.domain)
        node = Node("big_goal_client", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        client = ActionClient(node, FollowJointTrajectory, "/world_0/joint_trajectory_controller/follow_joint_trajectory")
        assert client.wait_for_server(timeout_sec=60)
        for _ in range(100):
            executor.spin_once(timeout_sec=0.01)
        print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores; {_versions()}; {time.strftime('%Y-%m-%d')}")
        before = rss_mb(worker)
        print(f"worker RSS before {before:.0f} MB")
        for k in range(opts.goals):
            goal = FollowJointTrajectory.Goal()
            goal.trajectory.joint_names = [f"joint{j}" for j in range(1, 7)]
            point = JointTrajectoryPoint(positions=[0.1] * 6)
            goal.trajectory.points = [point] * opts.points  # one object, serialized opts.points times
            peak, stop = [rss_mb(worker)], threading.Event()

            def watch(peak=peak, stop=stop) -> None:
                while not stop.is_set():
                    peak.append(rss_mb(worker))
                    time.sleep(0.05)

            threading.Thread(target=watch, daemon=True).start()
            sent = time.monotonic()
            future = client.send_goal_async(goal)
            executor.spin_until_future_complete(future, timeout_sec=300)
            handle = future.result()
            result = handle.get_result_async() if handle is not None and handle.accepted else None
            if result is not None:
                executor.spin_until_future_complete(result, timeout_sec=120)
            answered = time.monotonic() - sent
            stop.set()
            del goal
            what = result.result().result.error_string if result is not None and result.done() else "rejected"
            print(f"goal {k + 1} of {opts.points} points: {what!r} after {answered:.1f} s; worker RSS highest {max(peak):.0f} MB")
            start = time.monotonic()
            while time.monotonic() - start < opts.after:
                time.sleep(10.0)
                executor.spin_once(timeout_sec=0)
                print(f"  {time.monotonic() - start:5.0f} s after the answer: {rss_mb(worker):.0f} MB", flush=True)
    finally:
        rclpy.try_shutdown(context=context)
        proc.terminate()
        proc.wait(timeout=30)


if __name__ == "__main__":
    main()
