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

import os
import platform
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet import Batchsim, _versions, client_node, flood_args, keep_in_flight, start_flooder  # noqa: E402

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

    def send(k: int):
        goal = FollowJointTrajectory.Goal()
        goal.trajectory.joint_names = [f"joint{j}" for j in range(1, 7)]
        goal.trajectory.points = [JointTrajectoryPoint(positions=[0.2 if k % 2 else -0.2] * 6, time_from_start=Duration(sec=1))]
        return client.send_goal_async(goal)

    outcome = lambda f: "accepted" if f.result().accepted else "rejected"  # noqa: E731
    keep_in_flight(context, executor, send, outcome, ("accepted", "rejected"), outstanding, seconds)


def main() -> None:
    opts = flood_args(__doc__, 59, "goals", flood)
    if opts is None:  # this process was the flooder
        return
    from sensor_msgs.msg import JointState

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
        flooder = start_flooder(__file__, opts.world, opts.domain, opts.seconds + 5, opts.clients)
        time.sleep(2.0)  # its client found the server; it floods until after the window
        window("flooded", flooder)
        context.try_shutdown()
    finally:
        fleet.stop()


if __name__ == "__main__":
    main()
