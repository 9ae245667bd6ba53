"""`python -m ros_bridge.worker.description_topic TOPIC TIMEOUT [ROS ARGS ...]`: the robot
description someone publishes on TOPIC (std_msgs/String, reliable, transient local: what
robot_state_publisher latches on /robot_description), written to stdout.

Started by `batchsim --robot-description-topic` before anything else, so that the command
line itself never imports rclpy. Exit 0 with the text; 3 with one line on stderr when no
message came within TIMEOUT seconds.
"""

from __future__ import annotations

import sys
import time


def main(argv: list[str]) -> int:
    topic, timeout = argv[0], float(argv[1])
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    rclpy.init(args=[sys.argv[0], "--ros-args", *argv[2:]] if argv[2:] else None)
    try:
        node = rclpy.create_node("batchsim_robot_description")
        got: list[str] = []
        qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
        sub = node.create_subscription(String, topic, lambda msg: got.append(msg.data), qos)
        deadline = time.monotonic() + timeout
        while not got and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        if not got:
            print(f"no std_msgs/String on {sub.topic_name} within {timeout:g} s", file=sys.stderr)
            return 3
        sys.stdout.write(got[0])
        return 0
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
