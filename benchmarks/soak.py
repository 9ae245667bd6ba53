"""A soak: a fleet under random goals, switches, resets and a recording, and its processes' memory
over time (issue 47's review: the bridge worker grew in a straight line, 233 -> 257 MB in 15 min).

    .venv/bin/python benchmarks/soak.py --minutes 25

`batchsim --worlds 64 --record FILE` (the arm, its controllers, one bridge worker process, every
world's state recorded) on a private ROS domain; a client sends, to random worlds, a
FollowJointTrajectory goal to a random pose 10 times a second, a switch_controller (off, then on)
once a second and a world reset once a second, and checks that every goal gets its result. Every
`--every` seconds: the physics process's and the worker's resident memory (VmRSS), the goals sent
and answered so far. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import Batchsim, _versions, client_node, rss_mb, worker_pid  # noqa: E402

JOINTS = [f"joint{k}" for k in range(1, 7)]
JTC = "joint_trajectory_controller"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--every", type=float, default=60.0, help="seconds between two memory lines")
    p.add_argument("--domain", type=int, default=76)
    opts = p.parse_args()
    import rclpy
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from controller_manager_msgs.srv import SwitchController
    from rclpy.action import ActionClient
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectoryPoint

    record = Path(tempfile.mkdtemp()) / "soak.mcap"
    fleet = Batchsim(["--worlds", str(opts.worlds), "--bridge-workers", "1", "--quiet", "--record", str(record)], opts.domain)
    context = None
    try:
        fleet.wait_started(120)
        worker = worker_pid(fleet.proc.pid)
        context, node, executor = client_node(opts.domain, "soak_client")
        rng = random.Random(0)
        actions = [ActionClient(node, FollowJointTrajectory, f"/world_{w}/{JTC}/follow_joint_trajectory") for w in range(opts.worlds)]
        switches = [node.create_client(SwitchController, f"/world_{w}/controller_manager/switch_controller") for w in range(opts.worlds)]
        resets = [node.create_client(Trigger, f"/world_{w}/reset") for w in range(opts.worlds)]
        for client in actions:
            client.wait_for_server(timeout_sec=60)
        stats = {"sent": 0, "accepted": 0, "rejected": 0, "results": 0, "switches": 0, "resets": 0}

        def on_result(future) -> None:
            stats["results"] += 1

        def on_goal(future) -> None:
            handle = future.result()
            if handle is not None and handle.accepted:
                stats["accepted"] += 1
                handle.get_result_async().add_done_callback(on_result)
            else:
                stats["rejected"] += 1

        print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores; {_versions()}; {time.strftime('%Y-%m-%d')}; "
              f"{opts.worlds} arms, 1 bridge worker, recording {record}")  # fmt: skip
        print("| minutes | physics MB | worker MB | goals sent | accepted | rejected | results | switches | resets |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        start = time.monotonic()
        next_goal = next_second = next_line = start
        on = [True] * opts.worlds

        def line(t: float) -> None:
            s = stats
            print(f"| {(t - start) / 60:.1f} | {rss_mb(fleet.proc.pid):.0f} | {rss_mb(worker):.0f} | {s['sent']} | {s['accepted']} | "
                  f"{s['rejected']} | {s['results']} | {s['switches']} | {s['resets']} |", flush=True)  # fmt: skip

        while (now := time.monotonic()) - start < 60 * opts.minutes and fleet.proc.poll() is None:
            if now >= next_goal:
                next_goal += 0.1
                w = rng.randrange(opts.worlds)
                goal = FollowJointTrajectory.Goal()
                goal.trajectory.joint_names = JOINTS
                goal.trajectory.points = [JointTrajectoryPoint(positions=[rng.uniform(-0.5, 0.5) for _ in JOINTS],
                                                               time_from_start=Duration(sec=1))]  # fmt: skip
                actions[w].send_goal_async(goal).add_done_callback(on_goal)
                stats["sent"] += 1
            if now >= next_second:
                next_second += 1.0
                w = rng.randrange(opts.worlds)
                request = SwitchController.Request(strictness=1)
                (request.deactivate_controllers if on[w] else request.activate_controllers).append(JTC)
                on[w] = not on[w]
                switches[w].call_async(request).add_done_callback(lambda f: stats.__setitem__("switches", stats["switches"] + 1))
                resets[rng.randrange(opts.worlds)].call_async(Trigger.Request()).add_done_callback(
                    lambda f: stats.__setitem__("resets", stats["resets"] + 1)
                )
            if now >= next_line:
                next_line += opts.every
                line(now)
            executor.spin_once(timeout_sec=0.01)
        line(time.monotonic())
        if fleet.proc.poll() is not None:  # what ended it, in its own words
            print(f"# the fleet ended (exit {fleet.proc.returncode}) at minute {(time.monotonic() - start) / 60:.1f}; its last lines:")
            print("\n".join(f"#   {text}" for _, text in fleet.lines[-30:]), flush=True)
    finally:
        if context is not None:
            rclpy.try_shutdown(context=context)
        fleet.stop()


if __name__ == "__main__":
    main()
