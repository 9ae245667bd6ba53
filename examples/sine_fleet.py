"""Drive every arm of a running fleet: a different sine on each world's joints.

    batchsim --worlds 16                            # terminal 1: the fleet, default controllers
    python examples/sine_fleet.py --worlds 16       # terminal 2: this node
    python examples/watch_joint_states.py --world 0 # terminal 3 (or `ros2 topic echo /world_0/joint_states`)

One node, one publisher per world. By default it streams short trajectories
(trajectory_msgs/JointTrajectory, one point 2 ticks ahead) to each world's
`joint_trajectory_controller`, the controller the arm's default YAML gives it, as one
would drive a real ros2_control arm. With `--via commands` (for a fleet started with
`--controllers none`) it writes `/world_<i>/commands` (std_msgs/Float64MultiArray, one
value per command interface in `batchsim info arm` order: joint1..joint6 positions).
World i swings at its own frequency and phase, so you can tell the worlds apart. The
node runs on sim time (/clock), so the sines follow the simulation, paused or not.
"""

from __future__ import annotations

import argparse
import math
import sys

import rclpy
from builtin_interfaces.msg import Duration
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

NJOINT = 6
JOINTS = [f"joint{j + 1}" for j in range(NJOINT)]


class SineFleet(Node):
    """Publishes a sine per joint to every world at `rate` Hz, through its trajectory
    controller or its raw `commands` topic."""

    def __init__(self, worlds: int, namespace: str, amplitude: float, rate: float, via: str, controller: str):
        super().__init__("sine_fleet", parameter_overrides=[Parameter("use_sim_time", value=True)])
        self.amplitude = amplitude
        self.lead = 2.0 / rate  # each trajectory point lies two ticks ahead
        self.via = via
        if via == "trajectory":
            topic, msg_type = f"{controller}/joint_trajectory", JointTrajectory
            self.msg = JointTrajectory(joint_names=JOINTS)
            self.point = JointTrajectoryPoint(time_from_start=Duration(nanosec=int(self.lead * 1e9)))
            self.msg.points = [self.point]
        else:
            topic, msg_type = "commands", Float64MultiArray
            self.msg = Float64MultiArray(data=[0.0] * NJOINT)
        self.pubs = [self.create_publisher(msg_type, f"/{namespace.format(i=i)}/{topic}", 10) for i in range(worlds)]
        self.timer = self.create_timer(1.0 / rate, self.tick)  # sim-time timer
        self.get_logger().info(f"driving {worlds} worlds: /{namespace.format(i=0)}/{topic} ...")

    def tick(self) -> None:
        t = self.get_clock().now().nanoseconds * 1e-9
        if self.via == "trajectory":
            t += self.lead  # the point's value is where the arm should be when it is reached
        for i, pub in enumerate(self.pubs):
            freq = 0.2 + 0.05 * i  # Hz: each world its own
            values = [
                self.amplitude * math.sin(2 * math.pi * freq * t + 0.5 * j) * (1.0 if j < 3 else 0.5)
                for j in range(NJOINT)
            ]
            if self.via == "trajectory":
                self.point.positions = values  # header stamp 0: start now
            else:
                self.msg.data = values
            pub.publish(self.msg)


def main(args: list[str] | None = None) -> None:
    argv = remove_ros_args(sys.argv if args is None else args)[1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--namespace", default="world_{i}", help="the fleet's --namespace template")
    p.add_argument("--amplitude", type=float, default=0.8, help="radians")
    p.add_argument("--rate", type=float, default=50.0, help="Hz (sim time)")
    p.add_argument(
        "--via", choices=("trajectory", "commands"), default="trajectory",
        help="trajectory: the arm's joint_trajectory_controller (default fleet); "
        "commands: raw /<ns>/commands (a fleet run with --controllers none)",
    )
    p.add_argument("--controller", default="joint_trajectory_controller", help="the trajectory controller's name")
    opts = p.parse_args(argv)
    rclpy.init(args=args)
    node = SineFleet(opts.worlds, opts.namespace, opts.amplitude, opts.rate, opts.via, opts.controller)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
