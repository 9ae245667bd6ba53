"""Drive every arm of a running fleet: a different sine on each world's joints.

    batchsim --worlds 16 --controllers none        # terminal 1: the fleet, raw command topics
    python examples/sine_fleet.py --worlds 16       # terminal 2: this node
    ros2 topic echo /world_0/joint_states           # terminal 3, if you have the ros2 CLI

One node, one publisher per world on `/world_<i>/commands` (std_msgs/Float64MultiArray,
one value per command interface in `batchsim info arm` order: joint1..joint6 positions).
World i swings at its own frequency and phase, so you can tell the worlds apart. The
node runs on sim time (/clock), so the sines follow the simulation, paused or not.
"""

from __future__ import annotations

import argparse
import math
import sys

import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args
from std_msgs.msg import Float64MultiArray

NJOINT = 6


class SineFleet(Node):
    """Publishes a sine per joint to every world's `commands` topic at `rate` Hz."""

    def __init__(self, worlds: int, namespace: str, amplitude: float, rate: float):
        super().__init__("sine_fleet", parameter_overrides=[Parameter("use_sim_time", value=True)])
        self.amplitude = amplitude
        self.pubs = [
            self.create_publisher(Float64MultiArray, f"/{namespace.format(i=i)}/commands", 10)
            for i in range(worlds)
        ]
        self.msg = Float64MultiArray(data=[0.0] * NJOINT)
        self.timer = self.create_timer(1.0 / rate, self.tick)  # sim-time timer
        self.get_logger().info(f"driving {worlds} worlds: /{namespace.format(i=0)}/commands ...")

    def tick(self) -> None:
        t = self.get_clock().now().nanoseconds * 1e-9
        for i, pub in enumerate(self.pubs):
            freq = 0.2 + 0.05 * i  # Hz: each world its own
            self.msg.data = [
                self.amplitude * math.sin(2 * math.pi * freq * t + 0.5 * j) * (1.0 if j < 3 else 0.5)
                for j in range(NJOINT)
            ]
            pub.publish(self.msg)


def main(args: list[str] | None = None) -> None:
    argv = remove_ros_args(sys.argv if args is None else args)[1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--namespace", default="world_{i}", help="the fleet's --namespace template")
    p.add_argument("--amplitude", type=float, default=0.8, help="radians")
    p.add_argument("--rate", type=float, default=50.0, help="Hz (sim time)")
    opts = p.parse_args(argv)
    rclpy.init(args=args)
    node = SineFleet(opts.worlds, opts.namespace, opts.amplitude, opts.rate)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
