"""Print one world's joint positions as they change (for a machine without the ros2 CLI).

    python examples/watch_joint_states.py                 # /world_0/joint_states
    python examples/watch_joint_states.py --world 3 --seconds 5
"""

from __future__ import annotations

import argparse
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import JointState


class Watcher(Node):
    def __init__(self, topic: str, every: float):
        super().__init__("watch_joint_states")
        self.every, self.last = every, 0.0
        self.create_subscription(JointState, topic, self.show, 10)
        self.get_logger().info(f"waiting for {topic} ...")

    def show(self, msg: JointState) -> None:
        now = time.monotonic()
        if now - self.last < self.every:
            return
        self.last = now
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        joints = "  ".join(f"{n} {p:+.3f}" for n, p in zip(msg.name, msg.position, strict=False))
        print(f"sim {t:8.3f} s  {joints}", flush=True)


def main(args: list[str] | None = None) -> None:
    argv = remove_ros_args(sys.argv if args is None else args)[1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--world", type=int, default=0)
    p.add_argument("--namespace", default="world_{i}")
    p.add_argument("--every", type=float, default=0.25, help="wall seconds between lines")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long")
    opts = p.parse_args(argv)
    rclpy.init(args=args)
    node = Watcher(f"/{opts.namespace.format(i=opts.world)}/joint_states", opts.every)
    start = time.monotonic()
    try:
        while rclpy.ok() and (opts.seconds is None or time.monotonic() - start < opts.seconds):
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):  # Ctrl-C, SIGTERM
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
