"""The bridge workers: the only rclpy code of batchsim.

core.py        the Worker: one rclpy context and node serving a range of worlds
process.py     its process (`python -m ros_bridge.worker ...`, started by ros_bridge/host.py)
snapshot.py    the loop's snapshot, read; per-world outputs over it
messages.py    messages built in bulk as CDR bytes; incoming ones parsed into rows
trajectories.py  trajectories from topics and action goals, batched to the loop
tf.py          tf, tf_static, robot_description
actions.py     FollowJointTrajectory and GripperCommand servers
controller_manager.py  every world's controller_manager services
sensors.py, sensor_messages.py   camera images and lidar scans
services.py    requests to the loop (reset, pause, step, switch) and the services that wait for them
diagnostics.py rejected commands and /diagnostics
type_check.py  a remote endpoint built from another definition of our types, named
conflicts.py   another process already serving these worlds?
"""

from typing import Any

__all__ = ["Worker"]


def __getattr__(name: str) -> Any:
    # Worker, and rclpy with it, on first use: view.py (the web view's process) and
    # ros_bridge/view_file.py import from this package where ROS 2 is not installed
    if name == "Worker":
        from ros_bridge.worker.core import Worker

        return Worker
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
