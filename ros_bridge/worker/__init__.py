"""The bridge workers: the only rclpy code of batchsim.

core.py        the Worker: one rclpy context and node serving a range of worlds
process.py     its process (`python -m ros_bridge.worker ...`, __main__.py; started by ros_bridge/supervisor.py)
snapshot.py    the loop's snapshot, read; per-world outputs over it
messages.py    messages built in bulk as CDR bytes; incoming ones parsed into rows
intake.py      bounded intake: a flood on one world's topic costs that world only
trajectories.py  trajectories from topics and action goals, batched to the loop
on_request.py, graph_scan.py  per-world entities created when a client appears in the ROS graph
tf.py          tf, tf_static, robot_description
actions.py     FollowJointTrajectory and GripperCommand servers
controller_manager.py  every world's controller_manager services
controller_nodes.py  a node per controller and controller_manager, with their parameters
services.py    requests to the loop (reset, pause, step, switch) and the services that wait for them
simulation.py, wrench.py  mujoco_ros2_control's simulation services and ExternalWrenchPlugin service
sensors.py, sensor_messages.py   camera images and lidar scans
diagnostics.py rejected commands and /diagnostics
type_check.py  a remote endpoint built from another definition of our types, named
conflicts.py   another process already serving these worlds?
description_topic.py  the robot description taken from a topic (`--robot-description-topic`)
recorder.py    the recorder process (MCAP): mcap_file.py, schemas.py, sensor_recording.py, status_recording.py
replay.py      `batchsim replay FILE`
view.py        the web view's process; view_scene.py, its page (also `batchsim view FILE`'s); view_server.py, its server (same origin only, no share tunnel)
stacks.py      where a worker's threads spend their time (BATCHSIM_WORKER_STACKS)
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
