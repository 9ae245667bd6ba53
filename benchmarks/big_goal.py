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
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import Batchsim, _versions, client_node, rss_mb, worker_pid  # noqa: E402


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
    from trajectory_msgs.msg import JointTrajectoryPoint

    fleet = Batchsim(["--worlds", "2", "--bridge-workers", "1", "--quiet"], opts.domain)
    context = None
    try:
        fleet.wait_started(120)
        worker = worker_pid(fleet.proc.pid)
        assert worker is not None, "no bridge worker process"
        context, node, executor = client_node(opts.domain, "big_goal_client")
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
        if context is not None:
            rclpy.try_shutdown(context=context)
        fleet.stop()


if __name__ == "__main__":
    main()
