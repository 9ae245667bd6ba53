"""A flood of FollowJointTrajectory goals on one world against its neighbours' joint_states (issue 47).

    .venv/bin/python benchmarks/goal_flood.py --seconds 10

The review found a goal flood on one world cut its neighbours' joint_states from 100 to 81 a
second, with gaps up to 1.18 s (topics are bounded per world; actions were not). Since then a
world's goals have a budget (GOAL_RATE a second, ros_bridge/worker/services.py): the rest are
rejected at once, so the worker's one executor thread serves the other worlds.

`batchsim --worlds 16` (the arm, its controllers, one bridge worker: every world on the same
executor thread) on a private ROS domain. One process floods world 3's
`joint_trajectory_controller/follow_joint_trajectory` with `--clients` goals in flight, a new goal
sent as each is answered (accepted or rejected); meanwhile this process subscribes to worlds 0, 1
and 2's `joint_states` (100 Hz). Two windows: quiet, then flooded. Printed per window: the
neighbours' messages a second (their mean), the largest gap between two messages of one world,
and how many of the flood's goals were accepted and rejected. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import LOCALHOST, Batchsim, _pythonpath, _versions, client_node  # noqa: E402

JTC = "joint_trajectory_controller"
NEIGHBOURS = (0, 1, 2)


def flood(domain: int, world: int, seconds: float, outstanding: int) -> None:
    """The flooding process: `outstanding` goals in flight, a new one sent as each is answered."""
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from trajectory_msgs.msg import JointTrajectoryPoint

    context, node, executor = client_node(domain, "goal_flooder")
    client = ActionClient(node, FollowJointTrajectory, f"/world_{world}/{JTC}/follow_joint_trajectory")
    client.wait_for_server(timeout_sec=30)
    counts = {"accepted": 0, "rejected": 0}
    stop = time.monotonic() + seconds
    sent = 0

    def send() -> None:
        nonlocal sent
        goal = FollowJointTrajectory.Goal()
        goal.trajectory.joint_names = [f"joint{k}" for k in range(1, 7)]
        position = 0.2 if sent % 2 else -0.2
        goal.trajectory.points = [JointTrajectoryPoint(positions=[position] * 6, time_from_start=Duration(sec=1))]
        sent += 1
        client.send_goal_async(goal).add_done_callback(answered)

    def answered(future) -> None:
        counts["accepted" if future.result().accepted else "rejected"] += 1
        if time.monotonic() < stop:
            send()

    for _ in range(outstanding):
        send()
    while time.monotonic() < stop + 2.0:
        executor.spin_once(timeout_sec=0.05)
    context.try_shutdown()
    print(f"{counts['accepted']} {counts['rejected']}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="each window")
    p.add_argument("--clients", type=int, default=32, help="the flood's goals in flight")
    p.add_argument("--world", type=int, default=3, help="the flooded world")
    p.add_argument("--domain", type=int, default=59)
    p.add_argument("--flood", nargs=3, type=float, help=argparse.SUPPRESS)  # the flooding process
    opts = p.parse_args()
    if opts.flood:
        flood(int(opts.flood[0]), opts.world, opts.flood[1], int(opts.flood[2]))
        return
    from sensor_msgs.msg import JointState

    env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(opts.domain), "PYTHONPATH": _pythonpath()}
    fleet = Batchsim(["--worlds", "16", "--bridge-workers", "1", "--quiet"], opts.domain)
    try:
        fleet.wait_started(120)
        context, node, executor = client_node(opts.domain, "goal_flood_probe")
        heard: dict[int, list[float]] = {w: [] for w in NEIGHBOURS}
        for w in NEIGHBOURS:
            node.create_subscription(JointState, f"/world_{w}/joint_states", lambda msg, w=w: heard[w].append(time.monotonic()), 100)
        end = time.monotonic() + 30
        while time.monotonic() < end and not all(heard.values()):
            executor.spin_once(timeout_sec=0.05)
        print(f"# {platform.node() or 'host'}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; {_versions()}; "
              f"{time.strftime('%Y-%m-%d')}; 16 arms, 1 bridge worker, {opts.clients} goals in flight on world {opts.world}")  # fmt: skip
        print("| window | neighbours' joint_states a second | largest gap ms | flood accepted | flood rejected |")
        print("| --- | --- | --- | --- | --- |")

        def window(label: str, flooder: subprocess.Popen | None) -> None:
            start = time.monotonic()
            for times in heard.values():
                times.clear()
            while time.monotonic() < start + opts.seconds:
                executor.spin_once(timeout_sec=0.01)
            span = time.monotonic() - start
            rate = sum(len(t) for t in heard.values()) / len(heard) / span
            gaps = [max(b - a for a, b in zip([start, *t], [*t, start + span], strict=True)) for t in heard.values()]
            accepted, rejected = ("-", "-")
            if flooder is not None:
                accepted, rejected = flooder.communicate(timeout=120)[0].split()
            print(f"| {label} | {rate:.1f} | {1e3 * max(gaps):.0f} | {accepted} | {rejected} |", flush=True)

        window("quiet", None)
        flooder = subprocess.Popen([sys.executable, __file__, "--world", str(opts.world), "--flood", str(opts.domain),
                                    str(opts.seconds + 5), str(opts.clients)], stdout=subprocess.PIPE, text=True, env=env)  # fmt: skip
        time.sleep(2.0)  # its client found the server; it floods until after the window
        window("flooded", flooder)
        context.try_shutdown()
    finally:
        fleet.stop()


if __name__ == "__main__":
    main()
